"""The operator web UI (`rider ui`): a page served by the Rider, live over server-sent events."""
