"""Adapters beside the Zenoh bus: the FastData UDP stream, the SQLite event history and its
export, the Zenoh login files.
"""
