"""The length units a calibration file's translations may be in.

Apart from :mod:`mocapd.io.calibration_files` (which reads the files, and imports the camera model and its NumBa
kernel) so that the command line's parser can offer them as choices without that import.
"""

from __future__ import annotations

UNITS: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001}
"""Length units a calibration's translations may be in (metres per unit)."""
