"""Command-line interface: modules here only parse arguments and call the library."""
