"""Browser libraries the studio needs, found on this machine at run time (no CDN).

three.js comes from Debian's ``libjs-three`` (``/usr/share/javascript/three/``);
``GESTUREDB_THREE_JS`` may name another ``three.module.js`` (an operator's
setting, never a client's).
"""
from __future__ import annotations

import os

#: Where Debian's libjs-three puts the ES module build of three.js.
THREE_CANDIDATES = ("/usr/share/javascript/three/three.module.js",)


def find_three() -> str | None:
    """Path of ``three.module.js``, or None when no copy is installed."""
    env = os.environ.get("GESTUREDB_THREE_JS")
    for path in ([env] if env else []) + list(THREE_CANDIDATES):
        if os.path.isfile(path):
            return path
    return None
