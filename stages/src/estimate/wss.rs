//! WSS: weighted spatiotemporal similarity against simulated edge templates (SPEC.md section 4).
