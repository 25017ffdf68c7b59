"""treereg: marker-free registration of multi-station TLS scans of a single tree.

Pure computation, no UI. See README.md for the pipeline and `treereg_core.pipeline.register` for the
one-call API.
"""

__version__ = "0.1.0"
