"""Wire and file formats shared by device and ground. Pure code, no I/O."""
