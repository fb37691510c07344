import cv2
import numpy as np
import pytest
import torch

# one thread: the suite's tensors are tiny, and extra threads thrash on a loaded 2-core machine
torch.set_num_threads(1)


def _photos():
    from skimage import data

    return {
        "astronaut": data.astronaut(),
        "coffee": data.coffee(),
        "chelsea": data.chelsea(),
        "rocket": data.rocket(),
        "camera": data.camera(),
        "immunohistochemistry": data.immunohistochemistry(),
    }


@pytest.fixture(scope="session")
def photos() -> dict:
    """A few real photos bundled with scikit-image (never used to train the shipped models)."""
    return _photos()


@pytest.fixture(scope="session")
def image_dir(tmp_path_factory, photos):
    """Folder of small photos (jpg/png, colour and gray) for tiny training runs."""
    d = tmp_path_factory.mktemp("photos")
    for i, (name, img) in enumerate(photos.items()):
        img = cv2.resize(img, (160, int(160 * img.shape[0] / img.shape[1])), interpolation=cv2.INTER_AREA)
        if img.ndim == 3:
            img = img[..., ::-1]
        cv2.imwrite(str(d / f"{name}.{'png' if i % 2 else 'jpg'}"), img)
    return d


@pytest.fixture(scope="session")
def repo_script():
    """``load(path)``: a script of the repository (``eval/...``, ``train/...``) imported as a module
    (registered in ``sys.modules``, where its dataclasses look their module up)."""
    import importlib.util
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]

    def load(path: str):
        spec = importlib.util.spec_from_file_location(Path(path).stem, root / path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = module
        spec.loader.exec_module(module)
        return module

    return load


@pytest.fixture
def rng():
    return np.random.default_rng(0)


@pytest.fixture(autouse=True)
def no_network(monkeypatch):
    """Every test runs offline: opening an internet connection (a weight download) fails the test.
    Local sockets (data-loader workers, multiprocessing) are left alone."""
    import socket

    real_connect = socket.socket.connect

    def connect(self, address):
        if self.family in (socket.AF_INET, socket.AF_INET6):
            raise AssertionError(f"a test tried to connect to {address!r} (a download?)")
        return real_connect(self, address)

    def refuse(*args, **kwargs):
        raise AssertionError("a test tried to reach the network (a download?)")

    monkeypatch.setattr(socket.socket, "connect", connect)
    monkeypatch.setattr(socket, "create_connection", refuse)
    monkeypatch.setattr(socket, "getaddrinfo", refuse)
