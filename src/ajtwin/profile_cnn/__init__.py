"""ajtwin.profile_cnn"""
