"""Bounds that are hang guards, not timings: a test waits this long only when something is
broken, so a loaded machine never reaches them and no assertion depends on how fast it is."""

REPLY_S = 30.0  #: a link client's reply timeout where the reply must come
HANG_S = 60.0  #: a wait for a thread, a process or bytes to arrive
