"""keyframes"""
