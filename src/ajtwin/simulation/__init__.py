"""ajtwin.simulation"""
