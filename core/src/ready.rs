//! A service's ready line: the one machine-readable line a service prints on stdout once it
//! serves, `<name> ready key=value ...` (e.g. `learner ready grpc=127.0.0.1:50052
//! metrics=http://127.0.0.1:9090/metrics`). The services print it and `rfcl train`, `rfcl bench`
//! and the tests parse it with this one type.
use std::fmt;

const READY: &str = " ready";

#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ReadyLine {
    pub line: String,
}

impl ReadyLine {
    /// `<name> ready` and each `key=value`, in order.
    pub fn new(name: &str, fields: &[(&str, &str)]) -> Self {
        let mut line = format!("{name}{READY}");
        for (key, value) in fields {
            line.push_str(&format!(" {key}={value}"));
        }
        ReadyLine { line }
    }

    /// The ready line among a service's output lines: `None` for any other line.
    pub fn parse(line: &str) -> Option<Self> {
        let line = line.trim_end();
        let (name, rest) = line.split_once(READY)?;
        let whole_word = rest.is_empty() || rest.starts_with(' ');
        (whole_word && !name.is_empty() && !name.contains(' '))
            .then(|| ReadyLine { line: line.into() })
    }

    /// The value of `key=` on the line.
    pub fn field(&self, key: &str) -> Option<&str> {
        self.line
            .split_whitespace()
            .find_map(|word| word.strip_prefix(key)?.strip_prefix('='))
    }

    /// The value of `key=`; panics naming the line when it has none (for tests).
    pub fn expect_field(&self, key: &str) -> &str {
        self.field(key)
            .unwrap_or_else(|| panic!("no {key}= on the ready line {:?}", self.line))
    }

    /// `http://` + the gRPC address (`grpc=`), when the line has one.
    pub fn grpc_url(&self) -> Option<String> {
        self.field("grpc").map(|addr| format!("http://{addr}"))
    }
}

impl fmt::Display for ReadyLine {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.line)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_printed_line_parses_back_field_by_field() {
        let ready = ReadyLine::new(
            "curriculum-server",
            &[
                ("grpc", "127.0.0.1:4000"),
                ("dashboard", "http://127.0.0.1:4001/"),
            ],
        );
        assert_eq!(
            ready.to_string(),
            "curriculum-server ready grpc=127.0.0.1:4000 dashboard=http://127.0.0.1:4001/"
        );
        let parsed = ReadyLine::parse(&format!("{ready}\n")).unwrap();
        assert_eq!(parsed, ready);
        assert_eq!(parsed.field("grpc"), Some("127.0.0.1:4000"));
        assert_eq!(parsed.grpc_url().as_deref(), Some("http://127.0.0.1:4000"));
        assert_eq!(parsed.field("dashboard"), Some("http://127.0.0.1:4001/"));
        assert_eq!(parsed.field("metrics"), None);
        assert_eq!(ReadyLine::new("learner", &[]).grpc_url(), None);
    }

    #[test]
    fn other_output_is_not_a_ready_line() {
        assert!(ReadyLine::parse("learner ready").is_some());
        assert!(ReadyLine::parse("2026-12-06 INFO the learner is ready").is_none());
        assert!(ReadyLine::parse("warming up").is_none());
        assert!(ReadyLine::parse(" ready grpc=x").is_none());
        assert!(ReadyLine::parse("learner readying").is_none());
    }
}
