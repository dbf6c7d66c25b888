"""``python -m aiohal.pipe --fd N --target mod:func --options JSON``: the child of an NrtPeer."""

import sys

from aiohal.pipe.peer import main

sys.exit(main())
