"""Browser libraries the studio needs, found on this machine at run time (no CDN).

three.js comes from Debian's ``libjs-three`` (``/usr/share/javascript/three/``);
``GESTUREDB_THREE_JS`` may name another ``three.module.js`` (an operator's
setting, never a client's).
"""
from __future__ import annotations

import os

#: Where Debian's libjs-three puts the ES module build of three.js.
THREE_CANDIDATES = ("/usr/share/javascript/three/three.module.js",)


#: Where libjs-three puts the ES module of three.js's glTF loader, relative to ``three.module.js``'s folder.
GLTF_LOADER = os.path.join("examples", "jsm", "loaders", "GLTFLoader.js")


def find_gltf_loader(three: str | None) -> str | None:
    """Path of ``GLTFLoader.js`` (the studio loads a user's character with it) beside the three.js
    found by :func:`find_three` (Debian: ``/usr/share/javascript/three/examples/jsm/loaders/``), or None."""
    if three is None:
        return None
    path = os.path.join(os.path.dirname(os.path.realpath(three)), GLTF_LOADER)
    return path if os.path.isfile(path) else None


def find_three() -> str | None:
    """Path of ``three.module.js``, or None when no copy is installed."""
    env = os.environ.get("GESTUREDB_THREE_JS")
    for path in ([env] if env else []) + list(THREE_CANDIDATES):
        if os.path.isfile(path):
            return path
    return None
