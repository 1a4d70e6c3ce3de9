"""ajtwin.apps"""
