"""``python -m pcc_ros.cli ...`` runs ``pcc ...`` (as torchrun and the tests do)."""

import sys

from pcc_ros.cli.main import main

sys.exit(main())
