import sys

from omni_sfm.cli import main

sys.exit(main())
