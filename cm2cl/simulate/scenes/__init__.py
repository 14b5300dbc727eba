"""Built-in scene files."""
