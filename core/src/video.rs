//! An eval episode recorded as a video by an eval actor and kept by the curriculum server: what
//! it shows, and the file name that carries it (so a restarted server finds its videos again from
//! the directory alone).
use serde::{Deserialize, Serialize};

/// The largest video an eval actor may send (an animated GIF of a few hundred frames).
pub const MAX_EVAL_VIDEO_BYTES: usize = 8 << 20;
/// The largest episode return a video may carry, either sign: rfcl's reward is +1 per success
/// step, so a return is at most an episode's length; beyond this it is no return (and its file
/// name would outgrow the file system's limit).
pub const MAX_VIDEO_RETURN: f64 = 1e7;

/// What a recorded eval episode shows.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VideoMeta {
    pub policy_version: u64,
    /// Env steps the learner had received when it published the policy (the eval curves' key).
    pub env_steps: u64,
    /// The episode's reset seed (a held-out eval seed).
    pub seed: u64,
    pub success_at_end: bool,
    pub episode_return: f64,
    pub actor_id: u32,
}

impl VideoMeta {
    /// `v000012_steps40000_seed1000007_success_return41.0_actor2.gif`: sorted by policy version,
    /// readable in a listing, and parsed back by [`VideoMeta::from_file_name`].
    pub fn file_name(&self) -> String {
        let outcome = if self.success_at_end {
            "success"
        } else {
            "failure"
        };
        format!(
            "v{:06}_steps{}_seed{}_{outcome}_return{:.1}_actor{}.gif",
            self.policy_version, self.env_steps, self.seed, self.episode_return, self.actor_id
        )
    }

    /// The meta of a file named by [`VideoMeta::file_name`] (the return to its one decimal);
    /// `None` for any other name.
    pub fn from_file_name(name: &str) -> Option<VideoMeta> {
        let stem = name.strip_suffix(".gif")?;
        let mut parts = stem.split('_');
        let mut field = |prefix: &str| parts.next()?.strip_prefix(prefix).map(str::to_owned);
        let policy_version = field("v")?.parse().ok()?;
        let env_steps = field("steps")?.parse().ok()?;
        let seed = field("seed")?.parse().ok()?;
        let success_at_end = match field("")?.as_str() {
            "success" => true,
            "failure" => false,
            _ => return None,
        };
        let episode_return: f64 = field("return")?.parse().ok()?;
        let actor_id = field("actor")?.parse().ok()?;
        let meta = VideoMeta {
            policy_version,
            env_steps,
            seed,
            success_at_end,
            episode_return,
            actor_id,
        };
        (parts.next().is_none() && episode_return.is_finite() && meta.file_name() == name)
            .then_some(meta)
    }
}

/// One recorded eval episode: what it shows and the GIF's bytes.
#[derive(Debug, Clone, PartialEq)]
pub struct EvalVideo {
    pub meta: VideoMeta,
    pub gif: Vec<u8>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn file_names_round_trip_and_nothing_else_parses() {
        let meta = VideoMeta {
            policy_version: 12,
            env_steps: 40_000,
            seed: 1_000_007,
            success_at_end: true,
            episode_return: 41.04,
            actor_id: 2,
        };
        let name = meta.file_name();
        assert_eq!(
            name,
            "v000012_steps40000_seed1000007_success_return41.0_actor2.gif"
        );
        let back = VideoMeta::from_file_name(&name).unwrap();
        assert_eq!(
            back,
            VideoMeta {
                episode_return: 41.0,
                ..meta.clone()
            }
        );
        for other in [
            "v000012_steps40000_seed1000007_success_return41.0_actor2.mp4",
            "v000012_steps40000_seed1000007_maybe_return41.0_actor2.gif",
            "v12_steps40000_seed1000007_success_return41.0_actor2.gif",
            "v000012_steps40000_seed1000007_success_returnNaN_actor2.gif",
            "v000012_steps40000_seed1000007_success_return41.0_actor2_x.gif",
            "../v000012_steps40000_seed1000007_success_return41.0_actor2.gif",
            "snapshot.json",
        ] {
            assert_eq!(VideoMeta::from_file_name(other), None, "{other}");
        }
    }
}
