"""ajtwin.store"""
