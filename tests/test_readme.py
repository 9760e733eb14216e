"""The README's Python snippets run as they are written (against a real server on a free port
in place of 127.0.0.1:50051), so the first thing a user copies works."""
from __future__ import annotations

import pathlib
import re

import numpy as np

from tests.rpc._grpc_server import ServerThread

README = pathlib.Path(__file__).resolve().parents[1] / "README.md"


def test_every_python_snippet_of_the_readme_runs():
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    assert len(blocks) >= 2
    with ServerThread() as srv:
        for i, block in enumerate(blocks):
            namespace: dict = {}
            exec(compile(block.replace("127.0.0.1:50051", srv.target), f"README block {i}", "exec"),
                 namespace)
            # each snippet computes something: poses and their blends are finite unit poses
            for name in ("mean", "path", "means"):
                if name in namespace:
                    v = namespace[name]
                    assert v.shape[-1] == 8 and (abs(v[..., :4] ** 2).sum(-1) - 1 < 1e-12).all()
            if "look" in namespace:     # the World's: the box where both sources saw it
                look, box = namespace["look"], namespace["box"]
                np.testing.assert_allclose(look.pose * np.sign(look.pose[:4] @ box[:4]), box,
                                           atol=1e-9)
                assert (np.linalg.eigvalsh(look.covariance) > 0).all()
