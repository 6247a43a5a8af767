"""The ``rmrl`` command line."""
