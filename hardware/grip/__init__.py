"""Grip-force sources (``[glove] kind``, :mod:`hardware.grips`) and grip recordings.

- :mod:`.reader`: what every live source shares (the reader thread, the newest reading and its
  age, the reason to stop a trial); :mod:`.common`: their rig-file fields and force scale;
- :mod:`.steerlab_kind`: Steerlab's own glove unit (``hardware.glove``) as a kind;
- :mod:`.lsl_source`: any Lab Streaming Layer stream; :mod:`.text_source`: a text-line device
  on a serial port (its simulation: :mod:`.text_simulated`, POSIX ptys);
- :mod:`.paced`: the writer thread of the simulated grip devices; :mod:`.pty`: that thread
  writing into a pseudo-terminal, for the simulated serial devices;
- :mod:`.tekscan`: TekScan ASCII exports, read after the session.

Which kind fits which glove: ``docs/grip-sources.md``.
"""
