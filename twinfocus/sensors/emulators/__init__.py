"""Faithful loopback emulations of the sensors, written from the vendors' published formats.

- :class:`~twinfocus.sensors.emulators.fake_dca1000.FakeDca1000`: the DCA1000EVM's UDP command
  and data protocol on 127.0.0.1, with injected packet loss, reordering and duplicates.
- :class:`~twinfocus.sensors.emulators.fake_radar_cli.FakeRadarCli`: the mmWave SDK CLI on a
  pseudo-terminal, answering (and, on request, refusing) commands.
- :func:`~twinfocus.sensors.emulators.mmwcas_capture.write_mmwcas_capture`: MMWCAS capture
  folders in TI's layout.
- :func:`~twinfocus.sensors.emulators.radar_scene.simulate_mimo_frames`: what the radar sees
  of point scatterers, per TX-RX pair.
- :class:`~twinfocus.sensors.emulators.rig.EmulatedRadar` / :class:`~twinfocus.sensors.emulators.rig.EmulatedVio`:
  the whole handheld rig for ``launch/live.yaml``.

Command line: ``python -m twinfocus.sensors.emulators radar ...`` runs the emulated radar until
interrupted; ``python -m twinfocus.sensors.emulators capture DIR`` writes a simulated MMWCAS
capture folder and its trajectory file (for ``twinfocus convert``).
"""
