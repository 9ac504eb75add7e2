//! Simulated scenes: an edge or ridge crossing a taxel array (SPEC.md sections 1 and 8).
