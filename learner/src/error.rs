//! The learner library's error type.
use thiserror::Error;

#[derive(Debug, Error)]
pub enum LearnerError {
    /// A SAC / network option that cannot work (checked once, at construction).
    #[error("invalid learner config: {0}")]
    Config(String),
    /// Tensor or slice dims that do not match the networks or the buffer.
    #[error("shape mismatch: {0}")]
    Shape(String),
    /// Sampling from a buffer that holds no transition.
    #[error("cannot sample from the empty {0} buffer")]
    EmptyBuffer(&'static str),
    /// Demo actions outside [-1, 1] with `data_action_scale` set (spec 6.4).
    #[error("data_action_scale needs demo actions in [-1, 1]; demo action dim {dim} has {value}")]
    DemoActionRange { dim: usize, value: f32 },
    #[error("transition record: {0}")]
    Record(#[from] rfcl_core::transition::RecordError),
    #[error("libtorch: {0}")]
    Torch(#[from] tch::TchError),
}

pub type Result<T, E = LearnerError> = std::result::Result<T, E>;
