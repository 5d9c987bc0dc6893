"""``python -m jaxslam.cli``: the ``jaxslam`` command."""
import sys

from jaxslam.cli.parser import main

sys.exit(main())
