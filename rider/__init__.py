"""The Rider: the operator side. A typed client library, the `rider` CLI and the operator UI."""
