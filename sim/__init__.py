"""Simulated devices (first-class backends) and synthetic shapes with ground truth."""
