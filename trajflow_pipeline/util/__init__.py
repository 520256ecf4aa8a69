"""Small shared helpers: atomic outputs and progress display."""
