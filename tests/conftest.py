import os

import pytest

# Tests share the machine's two cores; numba/torch each default to all cores.
os.environ.setdefault("NUMBA_NUM_THREADS", str(os.cpu_count() or 1))


@pytest.fixture(autouse=True, scope="session")
def _template_cache_in_tmp(tmp_path_factory):
    """``focus`` caches templates in the user's cache folder; tests (and the processes they
    start) use a fresh one of their own instead."""
    old = os.environ.get("TWINFOCUS_CACHE_DIR")
    os.environ["TWINFOCUS_CACHE_DIR"] = str(tmp_path_factory.mktemp("template-cache"))
    yield
    if old is None:
        os.environ.pop("TWINFOCUS_CACHE_DIR", None)
    else:
        os.environ["TWINFOCUS_CACHE_DIR"] = old


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
