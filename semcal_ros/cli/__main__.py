import sys

from semcal_ros.cli import main

sys.exit(main())
