"""Command-line entry points of the library: argument parsing and printing over its packages."""
