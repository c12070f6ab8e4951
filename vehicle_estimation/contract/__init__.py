"""What crosses every boundary: the topic names and message contract, and the vehicle description."""
