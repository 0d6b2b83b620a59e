"""Star identification and attitude: colour pair/consensus matching (Enright & McVittie), 4-star K-vector
matching (Dong et al.), q-method attitude, and the solver front. Pure functions on arrays."""
