//! Fuzz body of `rpc_decode`: arbitrary bytes as the body of every rfcl.v1 message a service or
//! client decodes, prost-decoded and then converted into domain types by `rfcl_proto::convert`;
//! and as the `authorization` metadata the services' token guard checks. Shared by
//! `fuzz/fuzz_targets/rpc_decode.rs` and `proto/tests/fuzz_regressions.rs` (included by
//! `#[path]`).
//!
//! Properties: no panic; a refused message is an error; an accepted one satisfies the invariants
//! `convert` promises and converts back to the same wire message.
use prost::Message;
use rfcl_core::lease::{EpisodeReport, ResetArgs, ResetLease};
use rfcl_core::transition::RecordLayout;
use rfcl_proto::auth::{Guard, Token};
use rfcl_proto::convert::{action_scale, learner_addr, report_and_acquire};
use rfcl_proto::v1;

/// The token the guard expects (any valid one: the input never contains it by chance).
const TOKEN: &str = "0123456789abcdef0123456789abcdef";

/// Runs every decoder on `data`; returns one message per rejection, each prefixed with the wire
/// message it is about (prost's own errors name only the field path below it).
pub fn run(data: &[u8]) -> Vec<String> {
    let mut rejections = Vec::new();
    let mut refuse = |message: &str, error: String| rejections.push(format!("{message}: {error}"));

    // Curriculum service requests.
    match v1::AcquireRequest::decode(data) {
        Ok(wire) => {
            let domain = rfcl_core::lease::AcquireRequest::from(wire.clone());
            assert_eq!(v1::AcquireRequest::from(domain), wire);
        }
        Err(e) => refuse("AcquireRequest", e.to_string()),
    }
    match v1::EpisodeReport::decode(data) {
        Ok(wire) => match EpisodeReport::try_from(wire.clone()) {
            Ok(report) => check_report(&report, &wire),
            Err(e) => refuse("EpisodeReport", e.to_string()),
        },
        Err(e) => refuse("EpisodeReport", e.to_string()),
    }
    match v1::ReportAndAcquireRequest::decode(data) {
        Ok(wire) => match report_and_acquire(wire.clone()) {
            Ok((report, next)) => {
                check_report(
                    &report,
                    wire.report.as_ref().expect("accepted: has a report"),
                );
                assert_eq!(Some(v1::AcquireRequest::from(next)), wire.next);
            }
            Err(e) => refuse("ReportAndAcquireRequest", e.to_string()),
        },
        Err(e) => refuse("ReportAndAcquireRequest", e.to_string()),
    }
    match v1::WatchStageRequest::decode(data) {
        Ok(wire) => {
            if let Err(e) = learner_addr(&wire) {
                refuse("WatchStageRequest", e.to_string());
            }
        }
        Err(e) => refuse("WatchStageRequest", e.to_string()),
    }
    if let Err(e) = v1::GetStateRequest::decode(data) {
        refuse("GetStateRequest", e.to_string());
    }

    // Learner service requests.
    if let Err(e) = v1::GetRunInfoRequest::decode(data) {
        refuse("GetRunInfoRequest", e.to_string());
    }
    if let Err(e) = v1::WatchPolicyRequest::decode(data) {
        refuse("WatchPolicyRequest", e.to_string());
    }
    if let Err(e) = v1::HealthRequest::decode(data) {
        refuse("HealthRequest", e.to_string());
    }
    match v1::TransitionBatch::decode(data) {
        Ok(batch) => {
            // The records as the batch's own dims lay them out (the learner compares the dims
            // with the run's first, then reads exactly these views).
            let layout = RecordLayout::new(batch.obs_dim as usize, batch.action_dim as usize);
            match layout.view_batch(&batch.records) {
                Ok(views) => {
                    let n = views.len();
                    assert_eq!(n * layout.record_bytes(), batch.records.len());
                    for view in views {
                        let t = view.to_transition();
                        assert_eq!(t.obs.len(), layout.obs_dim);
                        assert_eq!(t.action.len(), layout.action_dim);
                        assert_eq!(t.next_obs.len(), layout.obs_dim);
                    }
                }
                Err(e) => refuse("TransitionBatch", format!("records: {e}")),
            }
        }
        Err(e) => refuse("TransitionBatch", e.to_string()),
    }

    // Replies a client converts (an actor trusts its curriculum and learner no more than they
    // trust it).
    match v1::ResetLease::decode(data) {
        Ok(wire) => match ResetLease::try_from(wire.clone()) {
            Ok(lease) => check_lease(&lease, &wire),
            Err(e) => refuse("ResetLease", e.to_string()),
        },
        Err(e) => refuse("ResetLease", e.to_string()),
    }
    match v1::ReportAndAcquireReply::decode(data) {
        Ok(reply) => {
            if let Some(wire) = reply.lease {
                match ResetLease::try_from(wire.clone()) {
                    Ok(lease) => check_lease(&lease, &wire),
                    Err(e) => refuse("ReportAndAcquireReply", e.to_string()),
                }
            }
        }
        Err(e) => refuse("ReportAndAcquireReply", e.to_string()),
    }
    match v1::RunInfo::decode(data) {
        Ok(info) => match action_scale(&info) {
            Ok(None) => assert!(info.action_scale.is_empty()),
            Ok(Some(scale)) => {
                assert_eq!(scale.len(), info.action_dim as usize);
                assert!(scale.iter().all(|s| s.is_finite() && *s > 0.0));
            }
            Err(e) => refuse("RunInfo", e.to_string()),
        },
        Err(e) => refuse("RunInfo", e.to_string()),
    }
    for (name, result) in [
        ("PolicyWeights", v1::PolicyWeights::decode(data).map(drop)),
        ("StageEvent", v1::StageEvent::decode(data).map(drop)),
        (
            "CurriculumState",
            v1::CurriculumState::decode(data).map(drop),
        ),
        ("HealthReply", v1::HealthReply::decode(data).map(drop)),
        ("PushSummary", v1::PushSummary::decode(data).map(drop)),
    ] {
        if let Err(e) = result {
            refuse(name, e.to_string());
        }
    }

    // The run token, as read from RFCL_TOKEN or a token file, and as presented in a call's
    // `authorization` metadata.
    let text = String::from_utf8_lossy(data);
    match Token::parse(&text, "in the fuzz input") {
        Ok(token) => {
            let t = token.expose();
            assert!(t.len() >= rfcl_proto::auth::MIN_TOKEN_CHARS);
            assert!(t.bytes().all(|b| b.is_ascii_graphic()));
        }
        Err(e) => refuse("authorization token", e.to_string()),
    }
    if let Ok(value) = tonic::metadata::MetadataValue::try_from(data) {
        use tonic::service::Interceptor;
        let mut guard = Guard::new(&Token::parse(TOKEN, "a constant").expect("a valid token"));
        let mut request = tonic::Request::new(());
        request.metadata_mut().insert("authorization", value);
        let admitted = guard.call(request).is_ok();
        let expected = format!("Bearer {TOKEN}");
        assert_eq!(admitted, data == expected.as_bytes());
        if !admitted {
            assert_eq!(guard.refused(), 1);
        }
    }
    rejections
}

/// An accepted report satisfies what `convert` checks and converts back to the same wire message.
fn check_report(report: &EpisodeReport, wire: &v1::EpisodeReport) {
    assert!(report.lease_id != 0 && report.length != 0);
    assert!(report.episode_return.is_finite());
    assert!(report.success_once || !report.success_at_end);
    assert_eq!(&v1::EpisodeReport::from(report.clone()), wire);
}

/// An accepted lease satisfies what `convert` checks and converts back to the same wire message
/// (options JSON compared as JSON: its formatting is not kept).
fn check_lease(lease: &ResetLease, wire: &v1::ResetLease) {
    assert!(lease.time_limit >= 1);
    assert!(lease.reset.options.is_object());
    let mut back = v1::ResetLease::from(lease.clone());
    let mut sent = wire.clone();
    let options = |args: &mut Option<v1::ResetArgs>| {
        args.take().map(|a| {
            let args = ResetArgs::try_from(a).expect("accepted once, accepted again");
            (args.seed, args.options)
        })
    };
    let (back_reset, sent_reset) = (options(&mut back.reset), options(&mut sent.reset));
    assert_eq!(
        back_reset,
        sent_reset.or(Some((None, ResetArgs::default().options)))
    );
    // NaN != NaN: compare the state bit for bit.
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&back.env_state), bits(&sent.env_state));
    back.env_state.clear();
    sent.env_state.clear();
    assert_eq!(back, sent);
}
