//! The learner library's error type.
//!
//! Every error enum of this crate keeps a cause either as its `source` or in its message, never
//! both, so a chain printed with `{:#}` (anyhow) or [`chain`] shows each cause once.
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
    #[error("transition record")]
    Record(#[from] rfcl_core::transition::RecordError),
    #[error("libtorch")]
    Torch(#[from] tch::TchError),
}

pub type Result<T, E = LearnerError> = std::result::Result<T, E>;

pub use rfcl_core::error::chain;

#[cfg(test)]
mod tests {
    use super::*;

    fn once(text: &str, cause: &str) {
        assert_eq!(text.matches(cause).count(), 1, "{cause:?} in {text:?}");
    }

    #[test]
    fn each_cause_is_printed_once() {
        let torch = tch::TchError::Torch("shape '[2, 3]' is invalid".into());
        let cause = torch.to_string();
        let err = LearnerError::from(torch);
        once(&format!("{:#}", anyhow::Error::new(err)), "is invalid");
        let err = LearnerError::from(tch::TchError::Torch("shape '[2, 3]' is invalid".into()));
        let text = chain(&err);
        once(&text, "is invalid");
        assert_eq!(text, format!("libtorch: {cause}"));

        let record = rfcl_core::transition::RecordLayout::new(2, 1)
            .view(&[0u8; 3])
            .map(|_| ())
            .unwrap_err();
        let cause = record.to_string();
        let text = format!("{:#}", anyhow::Error::new(LearnerError::from(record)));
        once(&text, &cause);
    }
}
