"""The st16-ground command line: the only package that imports everything."""
