"""Studies of a sensor preset's behaviour against published measurements of real devices."""
