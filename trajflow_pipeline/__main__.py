"""`python -m trajflow_pipeline ...`: the `trajflow` command where the console script is not installed (for example
a checkout on PYTHONPATH on a machine without network access)."""

from .cli.app import main

main()
