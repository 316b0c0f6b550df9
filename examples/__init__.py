"""Short scripts that use forcecal as a user would; ``tests/test_examples.py`` runs each one."""
