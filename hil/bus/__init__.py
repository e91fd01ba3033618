"""CAN bus layer: transports (python-can), the DBC protocol, and the loopback inter-process bus."""
