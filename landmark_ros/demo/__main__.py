"""``python -m landmark_ros.demo``: the simulated team demo (see ``landmark_ros.demo.run``)."""

import sys

from landmark_ros.demo.run import main

sys.exit(main())
