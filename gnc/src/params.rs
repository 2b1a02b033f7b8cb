//! Checks shared by the modules' `configure`.

/// Every named value is finite and positive; else the first that is not, named in the error.
pub fn require_positive(values: &[(&str, f64)]) -> Result<(), String> {
    match values.iter().find(|(_, v)| !(v.is_finite() && *v > 0.0)) {
        Some((k, v)) => Err(format!("{k} must be positive, got {v}")),
        None => Ok(()),
    }
}

/// Every named value is finite and not negative; else the first that is not, named in the error.
pub fn require_non_negative(values: &[(&str, f64)]) -> Result<(), String> {
    match values.iter().find(|(_, v)| !(v.is_finite() && *v >= 0.0)) {
        Some((k, v)) => Err(format!("{k} must be finite and not negative, got {v}")),
        None => Ok(()),
    }
}

/// Every value is finite; else "`what` must be finite".
pub fn require_finite(what: &str, values: &[f64]) -> Result<(), String> {
    if values.iter().all(|v| v.is_finite()) { Ok(()) } else { Err(format!("{what} must be finite")) }
}
