"""Files: atomic writes, paths from data made safe, checksums, and the readers and writers of the
generic formats (arrays: ``.npz``/``.npy``/PLY; documents: JSON/YAML; pictures: PNG through
matplotlib or OpenCV), so the numerics above take arrays and objects and never open files.

The lowest layer of the library: it imports nothing of TwinFocus but :mod:`twinfocus.errors`.
A format whose objects live higher up (a capture's :class:`~twinfocus.sensors.frames.RadarFrame`,
a trajectory's :class:`~twinfocus.motion.trajectory.Poses`, a focus's outputs) is read and written
by a format module in that layer, named ``*_files.py`` (``sensors/dca1000_files.py``,
``sensors/rosbag2_files.py``, ``sensors/trajectory_files.py``, ``focus/output_files.py``); the
file objects that are plain data (a scan, a camera, a rig, a board) bind this package's readers
in their ``load``/``save``.
"""
