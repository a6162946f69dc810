"""``python -m onboard.agent --id N --hub HOST --driver kh4|sim``."""
import sys

from onboard.agent.cli import main

sys.exit(main())
