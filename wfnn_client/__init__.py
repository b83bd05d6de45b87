"""Robot-side wfnn: acts on numpy at a fixed tick, learns and thinks (never needs torch)."""
