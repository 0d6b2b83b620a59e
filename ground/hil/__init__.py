"""Hardware in the loop: the tracker in a closed attitude loop (``run``; docs/hil.md)."""
