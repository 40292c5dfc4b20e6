"""Per-block speed and memory measurements, gathered by `ditch-drake bench`."""
