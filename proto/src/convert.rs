//! The one place where wire types become domain types and back. Every malformed message is
//! rejected here with an error that names the message and the field.
use rfcl_core::lease::{
    AcquireRequest, EpisodeReport, LeaseKind, ResetArgs, ResetLease, MAX_RESET_FAILURE_BYTES,
};
use rfcl_core::run_state::RunState;
use rfcl_core::video::{EvalVideo, VideoMeta, MAX_EVAL_VIDEO_BYTES, MAX_VIDEO_RETURN};

use crate::v1;

/// A wire message that does not describe a valid domain value.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("malformed {message}.{field}: {problem}")]
pub struct WireError {
    pub message: &'static str,
    pub field: &'static str,
    pub problem: String,
}

impl WireError {
    fn new(message: &'static str, field: &'static str, problem: impl Into<String>) -> Self {
        Self {
            message,
            field,
            problem: problem.into(),
        }
    }
}

impl From<WireError> for tonic::Status {
    fn from(err: WireError) -> Self {
        tonic::Status::invalid_argument(err.to_string())
    }
}

impl From<LeaseKind> for v1::LeaseKind {
    fn from(kind: LeaseKind) -> Self {
        match kind {
            LeaseKind::DemoState => v1::LeaseKind::DemoState,
            LeaseKind::Level => v1::LeaseKind::Level,
            LeaseKind::Eval => v1::LeaseKind::Eval,
        }
    }
}

fn lease_kind(raw: i32) -> Result<LeaseKind, WireError> {
    match v1::LeaseKind::try_from(raw) {
        Ok(v1::LeaseKind::DemoState) => Ok(LeaseKind::DemoState),
        Ok(v1::LeaseKind::Level) => Ok(LeaseKind::Level),
        Ok(v1::LeaseKind::Eval) => Ok(LeaseKind::Eval),
        Ok(v1::LeaseKind::Unspecified) | Err(_) => Err(WireError::new(
            "ResetLease",
            "kind",
            format!("expected DEMO_STATE, LEVEL or EVAL, got {raw}"),
        )),
    }
}

impl From<ResetArgs> for v1::ResetArgs {
    fn from(args: ResetArgs) -> Self {
        v1::ResetArgs {
            has_seed: args.seed.is_some(),
            seed: args.seed.unwrap_or(0),
            options_json: args.options.to_string(),
        }
    }
}

impl TryFrom<v1::ResetArgs> for ResetArgs {
    type Error = WireError;
    fn try_from(wire: v1::ResetArgs) -> Result<Self, WireError> {
        let options = if wire.options_json.trim().is_empty() {
            serde_json::Value::Object(Default::default())
        } else {
            match serde_json::from_str(&wire.options_json) {
                Ok(map @ serde_json::Value::Object(_)) => map,
                Ok(other) => {
                    return Err(WireError::new(
                        "ResetArgs",
                        "options_json",
                        format!("expected a JSON object, got {other}"),
                    ))
                }
                Err(err) => {
                    return Err(WireError::new(
                        "ResetArgs",
                        "options_json",
                        format!("invalid JSON: {err}"),
                    ))
                }
            }
        };
        Ok(ResetArgs {
            seed: wire.has_seed.then_some(wire.seed),
            options,
        })
    }
}

impl From<ResetLease> for v1::ResetLease {
    fn from(lease: ResetLease) -> Self {
        v1::ResetLease {
            lease_id: lease.lease_id,
            kind: v1::LeaseKind::from(lease.kind) as i32,
            demo_id: lease.demo_id,
            start_index: lease.start_index,
            env_state: lease.env_state,
            reset: Some(lease.reset.into()),
            time_limit: lease.time_limit,
            stage_epoch: lease.stage_epoch,
            stage: lease.stage,
            level: lease.level,
        }
    }
}

impl TryFrom<v1::ResetLease> for ResetLease {
    type Error = WireError;
    fn try_from(wire: v1::ResetLease) -> Result<Self, WireError> {
        let kind = lease_kind(wire.kind)?;
        if wire.time_limit == 0 {
            return Err(WireError::new(
                "ResetLease",
                "time_limit",
                "expected at least 1 step, got 0",
            ));
        }
        if kind == LeaseKind::DemoState && wire.env_state.is_empty() {
            return Err(WireError::new(
                "ResetLease",
                "env_state",
                "a DEMO_STATE lease needs the demo's env state, got none",
            ));
        }
        let reset = wire
            .reset
            .map(ResetArgs::try_from)
            .transpose()?
            .unwrap_or_default();
        Ok(ResetLease {
            lease_id: wire.lease_id,
            kind,
            demo_id: wire.demo_id,
            start_index: wire.start_index,
            env_state: wire.env_state,
            reset,
            time_limit: wire.time_limit,
            stage: wire.stage,
            stage_epoch: wire.stage_epoch,
            level: wire.level,
        })
    }
}

impl From<AcquireRequest> for v1::AcquireRequest {
    fn from(req: AcquireRequest) -> Self {
        v1::AcquireRequest {
            actor_id: req.actor_id,
            env_index: req.env_index,
            eval: req.eval,
        }
    }
}

impl From<v1::AcquireRequest> for AcquireRequest {
    fn from(wire: v1::AcquireRequest) -> Self {
        AcquireRequest {
            actor_id: wire.actor_id,
            env_index: wire.env_index,
            eval: wire.eval,
        }
    }
}

impl From<EpisodeReport> for v1::EpisodeReport {
    fn from(r: EpisodeReport) -> Self {
        v1::EpisodeReport {
            lease_id: r.lease_id,
            success_at_end: r.success_at_end,
            success_once: r.success_once,
            episode_return: r.episode_return,
            length: r.length,
            policy_version: r.policy_version,
            stage_epoch: r.stage_epoch,
            actor_id: r.actor_id,
            actor_env_steps: r.actor_env_steps,
            policy_env_steps: r.policy_env_steps,
            actor_sim_restarts: r.sim_restarts,
            reset_failure: r.reset_failure.unwrap_or_default(),
        }
    }
}

impl TryFrom<v1::EpisodeReport> for EpisodeReport {
    type Error = WireError;
    fn try_from(wire: v1::EpisodeReport) -> Result<Self, WireError> {
        if wire.lease_id == 0 {
            return Err(WireError::new(
                "EpisodeReport",
                "lease_id",
                "expected a lease id from Acquire, got 0",
            ));
        }
        if wire.reset_failure.len() > MAX_RESET_FAILURE_BYTES {
            return Err(WireError::new(
                "EpisodeReport",
                "reset_failure",
                format!(
                    "expected at most {MAX_RESET_FAILURE_BYTES} bytes, got {}",
                    wire.reset_failure.len()
                ),
            ));
        }
        let failed = !wire.reset_failure.is_empty();
        if failed && (wire.length != 0 || wire.success_once || wire.episode_return != 0.0) {
            return Err(WireError::new(
                "EpisodeReport",
                "reset_failure",
                format!(
                    "a lease whose reset failed ran no episode: expected length 0, no success and \
                     return 0, got length {}, success_once {}, return {}",
                    wire.length, wire.success_once, wire.episode_return
                ),
            ));
        }
        if !failed && wire.length == 0 {
            return Err(WireError::new(
                "EpisodeReport",
                "length",
                "expected at least 1 step, got 0",
            ));
        }
        if !wire.episode_return.is_finite() {
            return Err(WireError::new(
                "EpisodeReport",
                "episode_return",
                format!("expected a finite number, got {}", wire.episode_return),
            ));
        }
        if wire.success_at_end && !wire.success_once {
            return Err(WireError::new(
                "EpisodeReport",
                "success_once",
                "success_at_end is true, so success_once must be true",
            ));
        }
        Ok(EpisodeReport {
            lease_id: wire.lease_id,
            success_at_end: wire.success_at_end,
            success_once: wire.success_once,
            episode_return: wire.episode_return,
            length: wire.length,
            policy_version: wire.policy_version,
            stage_epoch: wire.stage_epoch,
            actor_id: wire.actor_id,
            actor_env_steps: wire.actor_env_steps,
            policy_env_steps: wire.policy_env_steps,
            sim_restarts: wire.actor_sim_restarts,
            reset_failure: failed.then_some(wire.reset_failure),
        })
    }
}

/// Spec 6.4's per-dimension action scale s as `RunInfo.action_scale` carries it: empty for
/// `None` (no scaling).
pub fn action_scale_to_wire(scale: Option<&[f32]>) -> Vec<f32> {
    scale.map(<[f32]>::to_vec).unwrap_or_default()
}

/// `RunInfo.action_scale` as the domain value: `None` when empty (no scaling), else s with one
/// value per action dimension (`RunInfo.action_dim`), each finite and > 0 (spec 6.4).
pub fn action_scale(info: &v1::RunInfo) -> Result<Option<Vec<f32>>, WireError> {
    let scale = &info.action_scale;
    if scale.is_empty() {
        return Ok(None);
    }
    if scale.len() != info.action_dim as usize {
        return Err(WireError::new(
            "RunInfo",
            "action_scale",
            format!(
                "expected {} values (action_dim) or none, got {}",
                info.action_dim,
                scale.len()
            ),
        ));
    }
    if let Some((d, s)) = scale
        .iter()
        .enumerate()
        .find(|(_, s)| !(s.is_finite() && **s > 0.0))
    {
        return Err(WireError::new(
            "RunInfo",
            "action_scale",
            format!("expected finite values > 0, got {s} for action dim {d}"),
        ));
    }
    Ok(Some(scale.clone()))
}

/// The longest learner address a `WatchStageRequest` may carry.
pub const MAX_LEARNER_ADDR_CHARS: usize = 256;

/// `WatchStageRequest.learner_addr` as the domain value: `None` when empty (an actor), else an
/// `http://` or `https://` URL with a host and a port, at most [`MAX_LEARNER_ADDR_CHARS`] long.
pub fn learner_addr(request: &v1::WatchStageRequest) -> Result<Option<String>, WireError> {
    let raw = request.learner_addr.as_str();
    if raw.is_empty() {
        return Ok(None);
    }
    let bad = |problem: String| WireError::new("WatchStageRequest", "learner_addr", problem);
    if raw.chars().count() > MAX_LEARNER_ADDR_CHARS {
        return Err(bad(format!(
            "expected at most {MAX_LEARNER_ADDR_CHARS} characters, got {}",
            raw.chars().count()
        )));
    }
    let uri: tonic::codegen::http::Uri = raw.parse().map_err(|e| {
        bad(format!(
            "expected a URL like http://host:50052, got {raw:?} ({e})"
        ))
    })?;
    let scheme_ok = matches!(uri.scheme_str(), Some("http" | "https"));
    let path_ok = matches!(uri.path(), "" | "/") && uri.query().is_none();
    if !scheme_ok || uri.host().is_none() || uri.port_u16().is_none() || !path_ok {
        return Err(bad(format!(
            "expected http://host:port or https://host:port, got {raw:?}"
        )));
    }
    Ok(Some(raw.to_string()))
}

/// `CurriculumState` as the domain value: its `json` holds the run's state.
pub fn run_state(wire: &v1::CurriculumState) -> Result<RunState, WireError> {
    serde_json::from_str(&wire.json).map_err(|e| {
        WireError::new(
            "CurriculumState",
            "json",
            format!("expected the run's state (stage, counts, demos, evals) as JSON: {e}"),
        )
    })
}

/// An `EvalVideo` as the domain value: a GIF (its magic first) of at most
/// [`MAX_EVAL_VIDEO_BYTES`], with a finite return within ±[`MAX_VIDEO_RETURN`].
pub fn eval_video(wire: v1::EvalVideo) -> Result<EvalVideo, WireError> {
    let bad = |field, problem: String| WireError::new("EvalVideo", field, problem);
    if wire.gif.len() > MAX_EVAL_VIDEO_BYTES {
        return Err(bad(
            "gif",
            format!(
                "expected at most {MAX_EVAL_VIDEO_BYTES} bytes, got {}",
                wire.gif.len()
            ),
        ));
    }
    if !wire.gif.starts_with(b"GIF89a") && !wire.gif.starts_with(b"GIF87a") {
        return Err(bad(
            "gif",
            format!(
                "expected an animated GIF (\"GIF89a\" first), got {} bytes starting {:?}",
                wire.gif.len(),
                String::from_utf8_lossy(&wire.gif[..wire.gif.len().min(6)])
            ),
        ));
    }
    if !wire.episode_return.is_finite() || wire.episode_return.abs() > MAX_VIDEO_RETURN {
        return Err(bad(
            "episode_return",
            format!(
                "expected a finite number within ±{MAX_VIDEO_RETURN:e} (an episode's return), \
                 got {:e}",
                wire.episode_return
            ),
        ));
    }
    Ok(EvalVideo {
        meta: VideoMeta {
            policy_version: wire.policy_version,
            env_steps: wire.policy_env_steps,
            seed: wire.seed,
            success_at_end: wire.success_at_end,
            episode_return: wire.episode_return,
            actor_id: wire.actor_id,
        },
        gif: wire.gif,
    })
}

impl From<EvalVideo> for v1::EvalVideo {
    fn from(v: EvalVideo) -> Self {
        v1::EvalVideo {
            actor_id: v.meta.actor_id,
            policy_version: v.meta.policy_version,
            policy_env_steps: v.meta.env_steps,
            seed: v.meta.seed,
            success_at_end: v.meta.success_at_end,
            episode_return: v.meta.episode_return,
            gif: v.gif,
        }
    }
}

/// The two halves of a `ReportAndAcquire` call.
pub fn report_and_acquire(
    wire: v1::ReportAndAcquireRequest,
) -> Result<(EpisodeReport, AcquireRequest), WireError> {
    let report = wire
        .report
        .ok_or_else(|| WireError::new("ReportAndAcquireRequest", "report", "missing"))?;
    let next = wire
        .next
        .ok_or_else(|| WireError::new("ReportAndAcquireRequest", "next", "missing"))?;
    Ok((EpisodeReport::try_from(report)?, next.into()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_curriculum_state_carries_the_run_state_and_anything_else_is_named() {
        let run = RunState {
            run_name: "r".into(),
            stage: 2,
            env_steps: 1234,
            train_success_rate: Some(0.5),
            ..Default::default()
        };
        let wire = v1::CurriculumState {
            json: serde_json::to_string(&run).unwrap(),
            ..Default::default()
        };
        assert_eq!(run_state(&wire), Ok(run));
        let e = run_state(&v1::CurriculumState {
            json: "{\"stage\": \"two\"}".into(),
            ..Default::default()
        })
        .unwrap_err();
        assert_eq!((e.message, e.field), ("CurriculumState", "json"));
        assert!(e.problem.starts_with("expected the run's state"), "{e}");
    }

    fn lease() -> ResetLease {
        let options = serde_json::json!({"goal": [1.0, 2.0]});
        ResetLease {
            lease_id: 7,
            kind: LeaseKind::DemoState,
            demo_id: 2,
            start_index: 40,
            env_state: vec![0.5, -1.0, 3.25],
            reset: ResetArgs {
                seed: Some(11),
                options,
            },
            time_limit: 17,
            stage: 1,
            stage_epoch: 0,
            level: 0,
        }
    }

    #[test]
    fn eval_videos_round_trip_and_bad_ones_name_their_field() {
        let video = EvalVideo {
            meta: VideoMeta {
                policy_version: 3,
                env_steps: 9000,
                seed: 1_000_002,
                success_at_end: false,
                episode_return: 0.0,
                actor_id: 2,
            },
            gif: b"GIF89a rest".to_vec(),
        };
        let wire: v1::EvalVideo = video.clone().into();
        assert_eq!(eval_video(wire.clone()).unwrap(), video);
        let err = eval_video(v1::EvalVideo {
            gif: b"\x89PNG\r\n".to_vec(),
            ..wire.clone()
        })
        .unwrap_err();
        assert_eq!((err.message, err.field), ("EvalVideo", "gif"));
        assert!(err.problem.contains("animated GIF"), "{err}");
        let err = eval_video(v1::EvalVideo {
            gif: vec![b'G'; MAX_EVAL_VIDEO_BYTES + 1],
            ..wire.clone()
        })
        .unwrap_err();
        assert!(err.problem.contains("at most 8388608 bytes"), "{err}");
        for extreme in [f64::NAN, 1e308, -2e7] {
            let err = eval_video(v1::EvalVideo {
                episode_return: extreme,
                ..wire.clone()
            })
            .unwrap_err();
            assert_eq!(err.field, "episode_return");
            assert!(err.problem.contains("within ±1e7"), "{err}");
            assert_eq!(
                tonic::Status::from(err).code(),
                tonic::Code::InvalidArgument
            );
        }
        // The largest return allowed still makes a file name the file system takes.
        let longest = VideoMeta {
            episode_return: -MAX_VIDEO_RETURN,
            env_steps: u64::MAX,
            seed: u64::MAX,
            policy_version: u64::MAX,
            actor_id: u32::MAX,
            ..video.meta
        };
        assert!(longest.file_name().len() < 255, "{}", longest.file_name());
    }

    #[test]
    fn lease_round_trips() {
        let wire: v1::ResetLease = lease().into();
        assert_eq!(wire.kind, v1::LeaseKind::DemoState as i32);
        assert_eq!(ResetLease::try_from(wire).unwrap(), lease());
    }

    #[test]
    fn seedless_reset_round_trips() {
        let mut l = lease();
        l.kind = LeaseKind::Eval;
        l.env_state.clear();
        l.reset = ResetArgs::default();
        let wire: v1::ResetLease = l.clone().into();
        assert!(!wire.reset.as_ref().unwrap().has_seed);
        assert_eq!(ResetLease::try_from(wire).unwrap(), l);
    }

    #[test]
    fn malformed_leases_name_the_field() {
        let mut wire: v1::ResetLease = lease().into();
        wire.kind = 0;
        let err = ResetLease::try_from(wire.clone()).unwrap_err();
        assert_eq!(
            err.to_string(),
            "malformed ResetLease.kind: expected DEMO_STATE, LEVEL or EVAL, got 0"
        );
        wire.kind = 1;
        wire.env_state.clear();
        assert_eq!(
            ResetLease::try_from(wire.clone()).unwrap_err().field,
            "env_state"
        );
        wire.env_state = vec![1.0];
        wire.reset.as_mut().unwrap().options_json = "[1,2]".into();
        assert_eq!(
            ResetLease::try_from(wire).unwrap_err().field,
            "options_json"
        );
    }

    #[test]
    fn report_and_acquire_needs_both_halves() {
        let err = report_and_acquire(v1::ReportAndAcquireRequest {
            report: None,
            next: Some(Default::default()),
        });
        assert_eq!(
            err.unwrap_err().to_string(),
            "malformed ReportAndAcquireRequest.report: missing"
        );
        let report = v1::EpisodeReport {
            lease_id: 1,
            length: 3,
            ..Default::default()
        };
        let err = report_and_acquire(v1::ReportAndAcquireRequest {
            report: Some(report.clone()),
            next: None,
        });
        assert_eq!(err.unwrap_err().field, "next");
        let (r, next) = report_and_acquire(v1::ReportAndAcquireRequest {
            report: Some(report),
            next: Some(v1::AcquireRequest {
                actor_id: 3,
                env_index: 1,
                eval: false,
            }),
        })
        .unwrap();
        assert_eq!((r.lease_id, next.actor_id, next.env_index), (1, 3, 1));
    }

    #[test]
    fn action_scale_round_trips_and_rejects_nonsense() {
        let info = |scale: Vec<f32>| v1::RunInfo {
            action_dim: 3,
            action_scale: scale,
            ..Default::default()
        };
        assert_eq!(
            action_scale(&info(action_scale_to_wire(None))).unwrap(),
            None
        );
        let s = [0.5f32, 1.0, 2.5];
        let wire = info(action_scale_to_wire(Some(&s)));
        assert_eq!(action_scale(&wire).unwrap(), Some(s.to_vec()));
        let err = action_scale(&info(vec![1.0, 2.0])).unwrap_err();
        assert_eq!(
            err.to_string(),
            "malformed RunInfo.action_scale: expected 3 values (action_dim) or none, got 2"
        );
        for bad in [0.0, -1.0, f32::NAN, f32::INFINITY] {
            let err = action_scale(&info(vec![1.0, bad, 1.0])).unwrap_err();
            assert_eq!((err.message, err.field), ("RunInfo", "action_scale"));
            assert!(err.problem.contains("action dim 1"), "{err}");
        }
    }

    #[test]
    fn report_round_trips_and_rejects_nonsense() {
        let report = EpisodeReport {
            lease_id: 3,
            success_at_end: true,
            success_once: true,
            episode_return: 4.0,
            length: 16,
            policy_version: 9,
            stage_epoch: 1,
            actor_id: 2,
            actor_env_steps: 1000,
            policy_env_steps: 800,
            sim_restarts: 2,
            reset_failure: None,
        };
        let wire: v1::EpisodeReport = report.clone().into();
        assert_eq!(wire.actor_sim_restarts, 2);
        assert_eq!(EpisodeReport::try_from(wire.clone()).unwrap(), report);
        let mut bad = wire.clone();
        bad.episode_return = f64::NAN;
        assert_eq!(
            EpisodeReport::try_from(bad).unwrap_err().field,
            "episode_return"
        );
        let mut bad = wire.clone();
        bad.success_once = false;
        assert_eq!(
            EpisodeReport::try_from(bad).unwrap_err().field,
            "success_once"
        );
        let mut bad = wire;
        bad.lease_id = 0;
        let status: tonic::Status = EpisodeReport::try_from(bad).unwrap_err().into();
        assert_eq!(status.code(), tonic::Code::InvalidArgument);
        assert!(status.message().contains("EpisodeReport.lease_id"));
    }

    #[test]
    fn a_failed_reset_is_reported_without_an_episode() {
        let failed = EpisodeReport {
            lease_id: 4,
            success_at_end: false,
            success_once: false,
            episode_return: 0.0,
            length: 0,
            policy_version: 0,
            stage_epoch: 1,
            actor_id: 2,
            actor_env_steps: 10,
            policy_env_steps: 0,
            sim_restarts: 0,
            reset_failure: Some("state field `collided` is invalid".into()),
        };
        let wire: v1::EpisodeReport = failed.clone().into();
        assert_eq!(EpisodeReport::try_from(wire.clone()).unwrap(), failed);
        let mut ran = wire.clone();
        ran.length = 5;
        let err = EpisodeReport::try_from(ran).unwrap_err();
        assert_eq!(err.field, "reset_failure");
        assert!(err.problem.contains("got length 5"), "{err}");
        let mut long = wire;
        long.reset_failure = "x".repeat(MAX_RESET_FAILURE_BYTES + 1);
        let err = EpisodeReport::try_from(long).unwrap_err();
        assert_eq!(
            err.to_string(),
            "malformed EpisodeReport.reset_failure: expected at most 2048 bytes, got 2049"
        );
    }

    #[test]
    fn a_learner_address_is_a_url_with_host_and_port_or_nothing() {
        let req = |addr: &str| v1::WatchStageRequest {
            learner_addr: addr.to_string(),
        };
        assert_eq!(learner_addr(&req("")), Ok(None));
        for good in [
            "http://learner:50052",
            "https://10.0.0.2:443",
            "http://[::1]:7/",
        ] {
            assert_eq!(
                learner_addr(&req(good)),
                Ok(Some(good.to_string())),
                "{good}"
            );
        }
        for bad in [
            "learner:50052",
            "ftp://learner:21",
            "http://learner",
            "http://learner:50052/path",
            "not a url",
        ] {
            let err = learner_addr(&req(bad)).unwrap_err();
            assert_eq!(
                (err.message, err.field),
                ("WatchStageRequest", "learner_addr"),
                "{bad}"
            );
        }
        let long = format!("http://{}:1", "a".repeat(MAX_LEARNER_ADDR_CHARS));
        assert!(learner_addr(&req(&long))
            .unwrap_err()
            .problem
            .contains("at most 256"));
    }
}
