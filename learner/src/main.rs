//! The `learner` service binary (not built yet: the library holds the SAC maths and replay).
fn main() {
    eprintln!("learner: the learner service is not built yet (rfcl-learner is a library for now)");
    std::process::exit(1);
}
