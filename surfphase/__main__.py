import sys

from surfphase.cli import main

sys.exit(main())
