"""The rig of thesis Chapter 8 (docs/explanation/thesis.md §7): BeagleBone Black I/O behind a safe UDP daemon.

- :mod:`.pins` — the pin map as data and its sysfs files under a configurable root;
- :mod:`.convert` — volts to PWM duty/DIR, ADC counts to stroke (calibrated);
- :mod:`.protocol` — the authenticated UDP datagrams (HMAC-SHA256, per-session challenge);
- :mod:`.daemon` — the I/O daemon ``rpr-board`` (C, ``c/board_*.c``) that owns the pins and
  enforces safety on its own: its build for this machine or the BeagleBone, and two ways to run it;
- :mod:`.build` — programs and libraries compiled for a target and cached (by :mod:`fmus`);
- :mod:`.faketree` and :mod:`.virtual` — a fake sysfs tree (sysfs and GPIO character devices) and
  a plant process: the virtual board;
- :mod:`.client` — a Python master of the protocol (tests, benchmarks);
- :mod:`.fmu` — the hardware FMU (hand-written C, built and cached by :mod:`fmus`).
"""
