"""Loop closure and the non-causal trajectory: place recognition (bag of binary words), PnP verification,
pose graph, covisibility, keyframe history and the final bundle adjustment. No transport in here."""
