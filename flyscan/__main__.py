"""``python -m flyscan``."""
import sys

from flyscan import main

sys.exit(main())
