import sys

from massspring.cli import main

sys.exit(main())
