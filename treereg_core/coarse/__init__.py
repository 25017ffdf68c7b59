"""Coarse registration (paper 2.1): projection images, rotation sequences, ORB matching, tie points, transform."""
