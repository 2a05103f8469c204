//! Headless Chromium (Debian's `chromium`, installed by scripts/setup.sh) for tests of pages the
//! services serve on loopback: a DOM dump or a screenshot of a real browser's rendering.
use std::path::Path;
use std::process::Command;

/// The Chromium binary.
pub fn chromium() -> &'static str {
    for candidate in ["/usr/bin/chromium", "/usr/bin/chromium-browser"] {
        if Path::new(candidate).exists() {
            return candidate;
        }
    }
    panic!("Debian's chromium is needed for the dashboard tests: run scripts/setup.sh (apt-get install chromium)");
}

/// Chromium headless with a fresh profile in `profile`, without the background connections this
/// closed network refuses.
pub fn headless(profile: &Path) -> Command {
    let mut cmd = Command::new(chromium());
    cmd.args([
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
    ])
    .arg(format!("--user-data-dir={}", profile.display()));
    cmd
}

/// The DOM of `url` as Chromium renders it (`--dump-dom`), with a fresh profile in `profile`.
pub fn dump_dom(profile: &Path, url: &str) -> String {
    let out = crate::child::output(headless(profile).arg("--dump-dom").arg(url));
    assert!(
        out.status.success(),
        "chromium failed on {url}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}
