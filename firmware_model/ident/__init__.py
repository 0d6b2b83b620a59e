"""Star identification and attitude: colour pair/consensus matching (seed 000), 4-star K-vector
matching (seed 001), q-method attitude, and the solver front. Pure functions on arrays."""
