"""Validation against independent vehicle-dynamics implementations (not our simulator).

* :mod:`.commonroad`: drives of the CommonRoad multi-body model (``vehiclemodels``, BMW 320i)
  written as bags in the topic contract.
* :mod:`.lateral`: offline comparison of the state cores with a textbook linear
  single-track KF on such a bag.
"""
