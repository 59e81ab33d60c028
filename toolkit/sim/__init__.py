"""Simulated house world: a robot with a monocular camera and a 2D lidar, with exact truth.

``simulate.simulate(SimConfig, out_dir)`` writes a sequence folder; ``stage.SimulateStage``
is the recipe stage ``simulate``; ``calib_capture.capture_calibration`` renders a
checkerboard calibration capture. See docs/simulator.md.
"""
