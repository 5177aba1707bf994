"""MCAP recording of every sigmaslam topic (``sigmaslam record``), recovery and reading back."""
