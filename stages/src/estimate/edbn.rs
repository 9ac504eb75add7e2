//! Event-based deep belief network after O'Connor et al. 2013 (SPEC.md section 5).
