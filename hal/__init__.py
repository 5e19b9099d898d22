"""The hardware boundary: the `Hal` protocol and its backends (simulator, Revolution Pi)."""
