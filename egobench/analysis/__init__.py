"""Measures that need no training or read trained runs: similarity to the paper's operating point, sensitivity curves, calibration inconsistency and reprojection, fidelity (resolved wavelength)."""
