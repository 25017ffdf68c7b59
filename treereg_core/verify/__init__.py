"""Verification: evidence that a registration is right (or not), and the verdict for each scan."""
