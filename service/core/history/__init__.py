"""What the loop records for the event history: the events, a command's held facts."""
