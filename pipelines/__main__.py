"""Command line: ``python -m pipelines <stage> --scene FILE --out DIR``."""
import sys

from pipelines.cli import main

sys.exit(main())
