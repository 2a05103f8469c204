//! Spec 5.5, 6.2, 6.4, 4.2, 12.7: replay sizes, uniform sampling, exact 50/50 minibatches,
//! demos as offline data, `data_action_scale`, and the stage transition.
use rfcl_core::demo::{Demo, ResetArgs, SuccessSource};
use rfcl_core::transition::{RecordLayout, Transition};
use rfcl_learner::replay::{data_action_scale, offline_from_demos};
use rfcl_learner::{LearnerError, Replay, ReplayBuffer};
use tch::{Device, Kind};

/// A buffer whose transition i has obs = [v; 3], action = [sign · v; 2], reward = sign · v and
/// next obs [v + 0.5; 3], for v = i + 1.
fn tagged_buffer(name: &'static str, n: usize, capacity: usize, sign: f32) -> ReplayBuffer {
    let mut buffer = ReplayBuffer::new(name, capacity, 3, 2).unwrap();
    for i in 0..n {
        let v = (i + 1) as f32;
        buffer
            .push(&[v; 3], &[sign * v; 2], sign * v, 1.0, &[v + 0.5; 3])
            .unwrap();
    }
    buffer
}

fn demo(actions: Vec<f32>, action_dim: usize, obs_dim: usize, success: Vec<bool>) -> Demo {
    let t = actions.len() / action_dim;
    Demo {
        episode_id: 0,
        obs_dim,
        action_dim,
        state_dim: 1,
        obs: (0..(t + 1) * obs_dim).map(|i| i as f32).collect(),
        actions,
        success,
        env_states: vec![0.0; t + 1],
        succeeded: true,
        success_source: SuccessSource::Steps,
        reset: ResetArgs::default(),
    }
}

#[test]
fn byte_size_is_capacity_times_record_bytes() {
    let buffer = ReplayBuffer::new("online", 1000, 42, 8).unwrap();
    assert_eq!(ReplayBuffer::record_bytes(42, 8), 4 * (42 + 42 + 8 + 1 + 1));
    assert_eq!(buffer.bytes(), 1000 * 376);
    assert_eq!(
        buffer.to_string(),
        "online replay: 0/1000 transitions × 376 B = 0.4 MB"
    );
    let replay = Replay::new(
        buffer,
        Some(ReplayBuffer::new("offline", 10, 42, 8).unwrap()),
        0,
    );
    assert_eq!(replay.bytes(), 1010 * 376);
    assert!(matches!(
        ReplayBuffer::new("online", 0, 42, 8),
        Err(LearnerError::Config(_))
    ));
}

#[test]
fn ring_overwrites_the_oldest_and_checks_dims() {
    let buffer = tagged_buffer("online", 7, 5, 1.0);
    assert_eq!((buffer.len(), buffer.capacity()), (5, 5));
    // Slots hold transitions 5, 6, 2, 3, 4 (tags 6, 7, 3, 4, 5): 0 and 1 were overwritten.
    let mut replay = Replay::new(buffer, None, 1);
    let batch = replay.sample(10, 20).unwrap();
    let mut seen: Vec<f32> = batch.reward.clone();
    seen.sort_by(f32::total_cmp);
    seen.dedup();
    assert_eq!(seen, vec![3.0, 4.0, 5.0, 6.0, 7.0]);
    assert!(matches!(
        replay
            .online
            .push(&[0.0; 2], &[0.0; 2], 0.0, 1.0, &[0.0; 3]),
        Err(LearnerError::Shape(_))
    ));
}

#[test]
fn sampling_is_uniform_with_replacement_and_seeded() {
    let n = 50;
    let mut a = Replay::new(tagged_buffer("online", n, n, 1.0), None, 42);
    let mut b = Replay::new(tagged_buffer("online", n, n, 1.0), None, 42);
    let mut c = Replay::new(tagged_buffer("online", n, n, 1.0), None, 43);
    let (x, y, z) = (
        a.sample(40, 250).unwrap(),
        b.sample(40, 250).unwrap(),
        c.sample(40, 250).unwrap(),
    );
    assert_eq!(x, y);
    assert_ne!(x, z);
    let mut counts = vec![0usize; n];
    for r in &x.reward {
        counts[*r as usize - 1] += 1;
    }
    // 10000 draws over 50 slots: 200 expected each; χ² with 49 dof stays far below 100.
    let chi2: f64 = counts
        .iter()
        .map(|&c| (c as f64 - 200.0).powi(2) / 200.0)
        .sum();
    assert!(chi2 < 100.0, "χ² = {chi2}");
    // Rows stay whole: obs, action, next obs of one transition.
    for r in 0..x.rows() {
        let i = x.reward[r];
        assert_eq!(&x.obs[r * 3..r * 3 + 3], &[i; 3]);
        assert_eq!(&x.action[r * 2..r * 2 + 2], &[i; 2]);
        assert_eq!(&x.next_obs[r * 3..r * 3 + 3], &[i + 0.5; 3]);
    }
}

#[test]
fn minibatches_are_exactly_half_online_half_offline() {
    let online = tagged_buffer("online", 30, 100, 1.0);
    let offline = tagged_buffer("offline", 20, 20, -1.0);
    let mut replay = Replay::new(online, Some(offline), 3);
    let (minibatches, size) = (8, 16);
    let batch = replay.sample(minibatches, size).unwrap();
    assert_eq!(batch.rows(), minibatches * size);
    // Online rows carry positive actions, offline rows negative ones; they alternate.
    for r in 0..batch.rows() {
        assert_eq!(batch.action[r * 2] > 0.0, r % 2 == 0, "row {r}");
    }
    let tensors = batch.to_tensors(Kind::Float, Device::Cpu);
    for m in 0..minibatches as i64 {
        let mb = tensors.minibatch(m, size as i64).unwrap();
        let online_rows = mb
            .action
            .select(1, 0)
            .gt(0.0)
            .sum(Kind::Int64)
            .int64_value(&[]);
        assert_eq!(
            online_rows,
            size as i64 / 2,
            "minibatch {m} is exactly 50/50"
        );
    }
    assert!(matches!(
        tensors.minibatch(minibatches as i64, size as i64),
        Err(LearnerError::Shape(_))
    ));
    // An odd minibatch cannot be split 50/50.
    assert!(matches!(replay.sample(2, 15), Err(LearnerError::Config(_))));
}

#[test]
fn without_offline_every_row_is_online_and_empty_buffers_are_refused() {
    let mut replay = Replay::new(tagged_buffer("online", 10, 10, 1.0), None, 5);
    let batch = replay.sample(4, 9).unwrap();
    assert_eq!(batch.rows(), 36);
    assert!(batch.action.iter().all(|&a| a >= 0.0));
    let mut empty = Replay::new(ReplayBuffer::new("online", 4, 3, 2).unwrap(), None, 0);
    assert!(matches!(
        empty.sample(1, 2),
        Err(LearnerError::EmptyBuffer("online"))
    ));
    let mut no_demos = Replay::new(
        tagged_buffer("online", 3, 4, 1.0),
        Some(ReplayBuffer::new("offline", 4, 3, 2).unwrap()),
        0,
    );
    assert!(matches!(
        no_demos.sample(1, 2),
        Err(LearnerError::EmptyBuffer("offline"))
    ));
}

#[test]
fn transition_records_are_stored_field_by_field() {
    let layout = RecordLayout::new(3, 2);
    let t = Transition {
        obs: vec![1.0, 2.0, 3.0],
        action: vec![-0.5, 0.25],
        reward: 1.0,
        next_obs: vec![4.0, 5.0, 6.0],
        mask: 1.0,
        stage_epoch: 0,
        actor_id: 3,
        policy_version: 9,
    };
    let mut bytes = vec![0u8; layout.record_bytes()];
    layout.encode(&t, &mut bytes).unwrap();
    let mut buffer = ReplayBuffer::new("online", 4, 3, 2).unwrap();
    buffer.push_record(&layout.view(&bytes).unwrap()).unwrap();
    let batch = Replay::new(buffer, None, 0).sample(1, 1).unwrap();
    assert_eq!(
        (batch.obs, batch.action, batch.next_obs),
        (t.obs, t.action, t.next_obs)
    );
    assert_eq!((batch.reward, batch.mask), (vec![1.0], vec![1.0]));
    let mut wrong = ReplayBuffer::new("online", 4, 5, 2).unwrap();
    assert!(wrong.push_record(&layout.view(&bytes).unwrap()).is_err());
}

/// Spec 6.4 on a hand-computed case with data_action_scale 1.25:
/// dim 0 peaks at |−0.5| → s = 1/(0.5·1.25) = 1.6; dim 1 reaches −1 → 1; dim 2 is always 0 → 1;
/// dim 3 peaks at 0.8 → 1/(0.8·1.25) = 1.
#[test]
fn data_action_scale_hand_computed_case() {
    let demos = [
        demo(
            vec![0.2, -1.0, 0.0, 0.8, -0.5, 0.3, 0.0, 0.1],
            4,
            2,
            vec![false, true],
        ),
        demo(vec![0.4, 0.9, 0.0, -0.7], 4, 2, vec![true]),
    ];
    let s = data_action_scale(&demos, 4, 1.25).unwrap();
    assert_eq!(s, vec![1.6, 1.0, 1.0, 1.0]);
    let bad = [demo(vec![0.2, 1.5, 0.0, 0.0], 4, 2, vec![true])];
    assert!(matches!(
        data_action_scale(&bad, 4, 1.25),
        Err(LearnerError::DemoActionRange { dim: 1, value }) if value == 1.5
    ));
}

/// Spec 6.2: demo step t → (obs_t, a_t · s, success_t, mask 1, obs_{t+1}), every step kept.
#[test]
fn demos_become_offline_transitions_in_agent_units() {
    let demos = [
        demo(vec![0.5, -0.25, 0.25, 0.1], 2, 3, vec![false, true]),
        demo(vec![-0.5, 0.0], 2, 3, vec![true]),
    ];
    let scale = [2.0, 1.0];
    let offline = offline_from_demos(&demos, Some(&scale)).unwrap();
    assert_eq!((offline.len(), offline.capacity()), (3, 3));
    let online = tagged_buffer("online", 1, 1, 1.0);
    let mut replay = Replay::new(online, Some(offline), 0);
    let batch = replay.sample(50, 2).unwrap();
    let mut seen = std::collections::HashSet::new();
    for r in (1..batch.rows()).step_by(2) {
        let obs = &batch.obs[r * 3..r * 3 + 3];
        let t = (obs[0] / 3.0) as usize;
        let (d, step) = if batch.action[r * 2] == -1.0 {
            (1, 0)
        } else {
            (0, t)
        };
        let expected_action = [
            demos[d].actions[step * 2] * 2.0,
            demos[d].actions[step * 2 + 1],
        ];
        assert_eq!(&batch.action[r * 2..r * 2 + 2], &expected_action);
        assert_eq!(
            &batch.next_obs[r * 3..r * 3 + 3],
            demos[d].obs_row(step + 1)
        );
        assert_eq!(
            batch.reward[r],
            if demos[d].success[step] { 1.0 } else { 0.0 }
        );
        assert_eq!(batch.mask[r], 1.0);
        seen.insert((d, step));
    }
    assert_eq!(seen.len(), 3, "every demo step is in the buffer");
}

/// Spec 4.2: offline := the stage-1 online buffer, the demos are dropped, online is emptied.
#[test]
fn stage_transition_moves_online_to_offline() {
    let online = tagged_buffer("online", 6, 8, 1.0);
    let demos = tagged_buffer("offline", 4, 4, -1.0);
    let mut replay = Replay::new(online, Some(demos), 0);
    replay.stage_transition(true, false).unwrap();
    assert!(replay.online.is_empty());
    assert_eq!(replay.online.capacity(), 8);
    let offline = replay.offline.as_ref().unwrap();
    assert_eq!(
        (offline.name(), offline.len(), offline.capacity()),
        ("offline", 6, 8)
    );
    assert!(matches!(
        replay.sample(1, 2),
        Err(LearnerError::EmptyBuffer("online"))
    ));
    replay
        .online
        .push(&[100.0; 3], &[100.0; 2], 100.0, 1.0, &[0.0; 3])
        .unwrap();
    let batch = replay.sample(20, 10).unwrap();
    for r in 0..batch.rows() {
        let expected_online = r % 2 == 0;
        assert_eq!(batch.reward[r] == 100.0, expected_online);
        // Offline rows are the stage-1 online transitions (tags 1..=6), never demos (negative).
        assert!(expected_online || (1.0..=6.0).contains(&batch.reward[r]));
    }

    // load_as_online_buffer keeps it online with no offline buffer; neither flag drops both.
    let mut keep = Replay::new(
        tagged_buffer("online", 6, 8, 1.0),
        Some(tagged_buffer("offline", 4, 4, -1.0)),
        0,
    );
    keep.stage_transition(false, true).unwrap();
    assert_eq!((keep.online.len(), keep.offline.is_none()), (6, true));
    let mut both = Replay::new(tagged_buffer("online", 6, 8, 1.0), None, 0);
    both.stage_transition(true, true).unwrap();
    assert_eq!(
        (both.online.len(), both.offline.as_ref().unwrap().len()),
        (6, 6)
    );
    let mut neither = Replay::new(tagged_buffer("online", 6, 8, 1.0), None, 0);
    neither.stage_transition(false, false).unwrap();
    assert_eq!((neither.online.len(), neither.offline.is_none()), (0, true));
}
