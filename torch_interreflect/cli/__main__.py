"""``python -m torch_interreflect.cli …`` (also ``torchrun … -m torch_interreflect.cli train-cc …``)."""

import sys

from .main import main

sys.exit(main())
