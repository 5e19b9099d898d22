"""The scan loop and what runs it: the cycle, its inbox, the runner, timing, the watchdog."""
