"""Real sensors: the TI radars, their capture boards, the ZED camera, trajectory files.

This is the one package of ``twinfocus`` that touches hardware (files written by capture
cards, UDP sockets, serial ports, USB). Each device is a small class with an iterator
(``frames()`` / ``poses()`` / ``pairs()``) so that a driver node backend is a few lines; the
numerics they feed stay plain functions on arrays.

Modules
-------
- :mod:`~twinfocus.sensors.frames`: the radar frame record, its flags, and the step from a MIMO
  frame (TX x RX x samples) to the monostatic-equivalent virtual channels of a scan.
- :mod:`~twinfocus.sensors.ti_mmwcas`: TI MMWCAS-RF-EVM cascade captures (``master_0000_data.bin``
  / ``_idx.bin`` and the three slaves), as written by the MMWCAS-DSP-EVM (TDA2) capture card.
- :mod:`~twinfocus.sensors.chirp_profile`: the chirp a capture was taken with, from the TI chirp
  profile of its configuration (mmWave Studio JSON or Lua, mmWave SDK ``.cfg``).
- :mod:`~twinfocus.sensors.ti_cli`: the mmWave SDK command line of single-chip radars over a
  serial port, and the ``.cfg`` file that drives it.
- :mod:`~twinfocus.sensors.dca1000`: the DCA1000EVM capture board's UDP protocol (commands and
  raw ADC streaming) with loss/reorder detection.
- :mod:`~twinfocus.sensors.dca1000_files`: DCA1000 capture files (mmWave Studio ``adc_data.bin``, the
  DCA1000EVM CLI's reordered and sequence-number record files, ``_Raw_N.bin`` splits).
- :mod:`~twinfocus.sensors.usb_devices`: which radars, capture boards and cameras are plugged in.
- :mod:`~twinfocus.sensors.zed`: ZED 2i through the ZED SDK, or its raw UVC side-by-side stream.
- :mod:`~twinfocus.sensors.trajectory_files`: TUM and EuRoC trajectory files.
- :mod:`~twinfocus.sensors.extrinsics`: the fixed camera-to-radar transform, and how to measure it.
- :mod:`~twinfocus.sensors.capture_to_scan`: radar frames + camera trajectory -> a scan
  (clock alignment, lever arm, virtual channels); the library side of ``twinfocus convert``.
- :mod:`~twinfocus.sensors.emulators`: faithful loopback emulations of the above for tests and
  for ``launch/live.yaml`` on machines without hardware.

Formats as implemented, and the TI / Stereolabs documents they come from: ``docs/sensors.md``.
"""
