"""Fuzz and fault campaigns against the emulated device and the ground client.

Each module has one job: :mod:`.traffic` makes valid and mutated NSP bytes, :mod:`.tally` counts
what a campaign did, :mod:`.device_proc` runs ``st16-device`` as a process, and the campaign
modules (:mod:`.nsp_fuzz`, :mod:`.upload_faults`, :mod:`.state_faults`, :mod:`.port_faults`,
:mod:`.tcp_faults`) each inject one class of fault. Tests run them short with fixed seeds;
``bench/bench_fuzz.py`` runs them long and prints the tally.
"""
