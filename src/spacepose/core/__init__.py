"""Pure computation: no file I/O, no plotting, no printing."""
