"""Simulation: the sensor simulator, the sky model, the device capture source, whole-sky and open-loop runs, frame writers."""
