"""TwinFocus: twin-reference autofocus for handheld 77 GHz MIMO-SAR imaging.

The numerics live in small modules named after what they hold: ``radar`` (chirp, MIMO
array, range compression), ``scan``, ``trajectory``, ``motion``, ``scene``, ``simulate``,
``grid``, ``backprojection``, ``autofocus``, ``metrics``. No sockets and no processes here.
"""

__version__ = "0.1.0"
