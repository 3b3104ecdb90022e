"""The laser stripe in a frame: its sub-pixel centre in every image column (paper, section II),
the estimators, their compiled kernels, and the geometric window of rows it can lie in.

This is the package's public face; its modules hold the code."""
from __future__ import annotations

from scanner_core.stripe.extractor import (METHODS, POLICIES, SIGNALS, BAYER_PATTERNS, StripeResult, extract, stripe_signal, demosaic, Reason, estimate_noise, isolated_runs)

__all__ = ["METHODS", "POLICIES", "SIGNALS", "BAYER_PATTERNS", "StripeResult", "extract", "stripe_signal", "demosaic", "Reason", "estimate_noise", "isolated_runs"]
