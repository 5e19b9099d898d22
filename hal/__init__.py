"""The hardware boundary: the `Hal` protocol, the IO map, the backends found by name
(`backends`) and the Revolution Pi backend (`revpi`); the simulator backend is `sim`."""
