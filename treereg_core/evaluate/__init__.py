"""Judging a registration: the paper's branch model (eq. 8) and the ICP baseline it is compared with."""
