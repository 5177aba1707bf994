"""The occupancy field two processes share: the mapping builds it, the back end's occupancy-to-point factors
query it (paper eq. 6-7). Block storage (:mod:`.blocks`), queries at points (:mod:`.query`), a received
``map/field`` message as a query-ready field (:mod:`.message`) and the depth points of the factors
(:mod:`.o2p_points`)."""
