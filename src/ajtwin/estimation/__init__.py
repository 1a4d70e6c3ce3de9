"""ajtwin.estimation"""
