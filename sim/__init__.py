"""The simulator wing: everything that only exists to play the machine's physical world.

The ride's physics with fault injection (`physics`), the simulator HAL (`hal`), the world
behind a RevPi process image (`procimg`, `world`, wired by `config.rsc`), the `sim/<fault>`
requests (`faults`, the bus's `SimPort`) and `machine demo` (`demo`). It may import `hal`,
`schema` and `service`; production reaches it only through `service.simwing`, lazily, so a
hardware install never loads it (tests/test_layering.py).
"""
