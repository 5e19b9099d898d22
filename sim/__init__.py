"""The simulator, a HAL backend: everything that only exists to play the machine's physical world.

Its settings (`settings`, the `[hal.sim]` table), the ride's physics with fault injection
(`physics`), the simulator HAL (`hal`), the world behind a RevPi process image (`procimg`,
`world`, wired by `config.rsc`) and the `sim/<fault>` requests (`faults`). `backend` ties them
into the backend registered as `sim` (pyproject.toml): production finds it by that name
(`hal.backends`) and never imports it. It imports only `hal` and `schema`
(tests/test_layering.py).
"""
