"""``python -m vehicle_estimation`` is the launcher, ``vehicle-estimation``."""

from vehicle_estimation.cli import main

raise SystemExit(main())
