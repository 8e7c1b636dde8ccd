"""File I/O, run folders, plots, reports, benchmarks and campaigns on top of the core."""
