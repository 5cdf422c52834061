"""The ``deltar`` command line."""
