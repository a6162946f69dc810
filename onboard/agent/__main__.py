"""``python -m onboard.agent --id N --hub HOST --driver kh4|sim``."""
import sys

try:
    from onboard.agent.cli import main
except ImportError as err:          # a robot set up without the agent's packages: say which, in one line
    sys.exit(f"agent: error: {err}: the agent needs Python >= 3.9 with numpy, pyzmq, pyyaml and filterpy "
             f"(docs/lab.md, 'Setting up a robot')")

sys.exit(main())
