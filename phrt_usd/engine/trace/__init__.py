"""Embree (embreex): the BVH with its float32 boundary, and the tracer of
reflection, shadow and primary rays."""
