import sys

from app.cli import main

if __name__ == "__main__":  # not when a spawned child imports it as __mp_main__
    sys.exit(main())
