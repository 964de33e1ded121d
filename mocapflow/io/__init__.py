"""File formats in and out: C3D, TRC, BVH, skeleton JSON."""
