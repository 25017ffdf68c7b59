"""Shared maths: rigid transforms, robust estimation over point pairs, normals and voxels, losses."""
