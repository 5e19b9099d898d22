"""The machine daemon: typed IO, devices, controllers, the state machine, the scan loop, the bus."""
