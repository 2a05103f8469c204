//! Error display shared by the services.

/// `err` and its sources, joined by ": " (what `{:#}` prints for an `anyhow::Error`): for logs
/// and messages built from errors that are not turned into an `anyhow::Error`.
pub fn chain(err: &(dyn std::error::Error + 'static)) -> String {
    let mut out = err.to_string();
    let mut cause = err.source();
    while let Some(e) = cause {
        out.push_str(": ");
        out.push_str(&e.to_string());
        cause = e.source();
    }
    out
}
