"""Ground-side star catalog tools: sources, colour model, design, build and analysis."""
