"""The machine's core: the scan loop, the control state machine, its controllers and
devices, the live parameters and what persists.
"""
