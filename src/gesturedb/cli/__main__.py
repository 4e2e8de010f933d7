import sys

from gesturedb.cli.main import main

sys.exit(main())
