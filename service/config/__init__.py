"""The machine config: its model (`model`), the check (`validate`), the one loader (`load`)."""
