import os

import pytest

# Tests share the machine's two cores; numba/torch each default to all cores.
os.environ.setdefault("NUMBA_NUM_THREADS", str(os.cpu_count() or 1))


def pytest_collection_modifyitems(config, items):
    try:
        import torch

        has_cuda = torch.cuda.is_available()
    except Exception:  # pragma: no cover - torch is a hard dependency
        has_cuda = False
    skip_gpu = pytest.mark.skip(reason="needs a CUDA device")
    for item in items:
        if "gpu" in item.keywords and not has_cuda:
            item.add_marker(skip_gpu)
