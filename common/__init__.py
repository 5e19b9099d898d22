"""What the daemon and the Rider share that is not on the wire: how each side opens its Zenoh
session (`zenoh_session`), its credentials from the environment (`credentials`), Zenoh's runtime
layout (`runtime`) and the Python state of Zenoh's callback threads (`threadstate`).

It imports none of the project's packages; `zenoh` only in `zenoh_session`
(tests/test_layering.py). Wire models and the codec stay in `schema`.
"""
