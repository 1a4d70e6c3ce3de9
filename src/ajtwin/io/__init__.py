"""ajtwin.io"""
