"""The simulator: a Carmine-like RGB-D camera over a table, the paper's eight objects.
May import ``core``, ``data`` and ``sim``."""
