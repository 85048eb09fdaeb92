"""Reading and writing frames, sweeps and cubes."""
