"""Ground side: catalogs, serial client and console, simulations and analyses."""
