"""ajtwin.cfd"""
