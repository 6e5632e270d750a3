import sys

from lensfit.cli import main

sys.exit(main())
