import os

import torch

# Under pytest-xdist every worker is its own process: one torch thread each keeps 2 cores from being
# oversubscribed (spinning intra-op threads make small-tensor code many times slower).
if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)
