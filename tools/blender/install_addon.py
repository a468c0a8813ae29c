"""Install and enable the mocapd live-link add-on in Blender, and save the preferences.

Run it with Blender (docs/blender.md)::

    blender --background --python tools/blender/install_addon.py

or with any Python that has the ``bpy`` module. It zips ``tools/blender/mocapd_link/`` and installs the zip as
Blender's own "Install from Disk" does (``preferences.addon_install``), so Blender keeps a copy in its user
add-ons folder and the checkout can move afterwards.
"""

from __future__ import annotations

import tempfile
import zipfile
from pathlib import Path

import bpy

ADDON = Path(__file__).resolve().parent / "mocapd_link"
MODULE = "mocapd_link"


def build_zip(dest: Path) -> Path:
    """The add-on as an installable zip (``mocapd_link/*.py``), written to ``dest``."""
    with zipfile.ZipFile(dest, "w", zipfile.ZIP_DEFLATED) as z:
        for f in sorted(ADDON.glob("*.py")):
            z.write(f, f"{MODULE}/{f.name}")
    return dest


def install(save: bool = True) -> None:
    """Install, enable and (``save``) keep it enabled in the user preferences."""
    with tempfile.TemporaryDirectory() as tmp:
        zipped = build_zip(Path(tmp) / f"{MODULE}.zip")
        bpy.ops.preferences.addon_install(filepath=str(zipped), overwrite=True)
    bpy.ops.preferences.addon_enable(module=MODULE)
    if save:
        bpy.ops.wm.save_userpref()
    print(f"mocapd live link installed and enabled (Blender {bpy.app.version_string})")


if __name__ == "__main__":
    install()
