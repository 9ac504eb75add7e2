//! Signal stages: normalization, filters, derivatives and drives (SPEC.md section 2).
