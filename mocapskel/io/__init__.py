"""Readers and writers: C3D, TRC, BVH, skeleton files."""
