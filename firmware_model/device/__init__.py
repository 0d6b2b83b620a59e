"""The device shell: command dispatch, memory map, slots and transfers, sequence runner, link transports, capture sources, the command line."""
