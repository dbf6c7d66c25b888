"""The tick core: the loop's lifecycle and tick, the clock that schedules it, the command
limits, target extrapolation, velocity feed-forward, tick timing and the real-time settings."""
