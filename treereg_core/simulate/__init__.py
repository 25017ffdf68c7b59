"""Simulated TLS stations with ground truth: procedural trees, a ray-cast scanner, benchmark cases."""
