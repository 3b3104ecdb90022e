"""Small numeric kernels the frame-rate searches share, compiled with numba: dense solves of
small least-squares systems, and max-pooling with connected components over a frame.

This is the package's public face; its modules hold the code."""
from __future__ import annotations


__all__ = []
