"""Test harnesses: the ``st16`` pytest plugin for users' tests (:mod:`.pytest_plugin`, the
``pytest11`` entry point; docs/testing.md), and the project's own fault campaigns against the
emulated device and the ground client, and the device run as a process. The tests run them short with
fixed seeds; ``bench/bench_fuzz.py`` runs them long and prints the tally.

Each module has one job: :mod:`.traffic` makes valid and mutated NSP bytes, :mod:`.tally` counts
what a campaign did, :mod:`.device_proc` runs ``st16-device`` as a process, and the campaign
modules (:mod:`.nsp_fuzz`, :mod:`.upload_faults`, :mod:`.state_faults`, :mod:`.port_faults`,
:mod:`.tcp_faults`, :mod:`.commit_kill`, :mod:`.feed_faults`) each inject one class of fault.
"""
