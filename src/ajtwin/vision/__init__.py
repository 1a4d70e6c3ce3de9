"""ajtwin.vision"""
