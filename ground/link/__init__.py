"""Talking to a device: the NSP client, the interactive console and the exchange log."""
