"""Baseline servers measured side by side with the daemon: each a small process of its own."""
