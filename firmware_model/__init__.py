"""The emulated star tracker: device shell and detection-to-attitude pipeline."""
