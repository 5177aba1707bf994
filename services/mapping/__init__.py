"""Occupancy submapping (paper sec. IV-B, IV-E; eq. 2-4): algorithm modules without transport, and the
``sigmaslam mapping`` service shell in :mod:`services.mapping.service`."""
