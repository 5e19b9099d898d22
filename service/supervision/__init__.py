"""Running the machine: the assembled daemon (`daemon`) and the supervisor that restarts
it (`supervisor`).
"""
