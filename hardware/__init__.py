"""The rig of thesis Chapter 8 (SPEC §7): BeagleBone Black I/O behind a safe UDP daemon.

- :mod:`.pins` — the pin map as data and its sysfs files under a configurable root;
- :mod:`.convert` — volts to PWM duty/DIR, ADC counts to stroke (calibrated);
- :mod:`.protocol` — the authenticated UDP datagrams (HMAC-SHA256, per-session nonce);
- :mod:`.daemon` — the I/O daemon that owns the pins and enforces safety on its own;
- :mod:`.faketree` and :mod:`.virtual` — a fake sysfs tree and a plant process: the virtual board;
- :mod:`.fmu` — the hardware FMU (hand-written C, built and cached by :mod:`fmus`).
"""
