import sys

from robotdemo.cli import main

sys.exit(main())
