import sys

from crowdbake.cli import main

sys.exit(main())
