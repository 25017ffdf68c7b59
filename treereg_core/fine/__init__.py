"""Fine registration (paper 2.2): slices, arcs, circle and cylinder fits, and the fine pose."""
