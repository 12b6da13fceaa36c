"""The ``graylight`` command line: one module per command group, each registering its sub-commands."""
