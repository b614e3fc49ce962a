"""CarmReg logic: everything that computes. Imports no Qt.

Frames and units (see README "Frames and units"):
- world = the CT patient frame, LPS millimetres;
- detector pixels (column, row) = (u, v), 0-based, pixel centres at integer coordinates,
  row 0 at the top; arrays indexed image[row, column];
- angles in degrees at every interface, radians only inside functions.
"""

__version__ = "0.1.0"
