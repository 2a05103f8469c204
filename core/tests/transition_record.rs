//! The transition record layout: pinned sizes and offsets, round trips, length errors.

use proptest::prelude::*;
use rfcl_core::transition::{RecordError, RecordLayout, Transition};

fn transition(layout: RecordLayout, seed: f32) -> Transition {
    let values = |n: usize, tag: f32| (0..n).map(|i| seed + tag + i as f32 * 0.5).collect();
    Transition {
        obs: values(layout.obs_dim, 0.0),
        action: values(layout.action_dim, 100.0),
        reward: 1.0,
        next_obs: values(layout.obs_dim, 200.0),
        mask: 0.0,
        stage_epoch: 3 + seed as u64,
        actor_id: 17,
        policy_version: 0x0102_0304_0506_0708,
    }
}

#[test]
fn record_bytes_is_pinned_for_obs_42_action_8() {
    let layout = RecordLayout::new(42, 8);
    assert_eq!(RecordLayout::HEADER_BYTES, 32);
    assert_eq!(layout.record_bytes(), 32 + 4 * (42 + 8 + 42));
    assert_eq!(layout.record_bytes(), 400);
}

#[test]
fn records_are_padded_to_a_multiple_of_8() {
    // 32 + 4·(2·1 + 1) = 44 → 48.
    assert_eq!(RecordLayout::new(1, 1).record_bytes(), 48);
    assert_eq!(RecordLayout::new(0, 0).record_bytes(), 32);
    for (d, a) in [(7, 2), (39, 4), (45, 24), (51, 7)] {
        assert_eq!(RecordLayout::new(d, a).record_bytes() % 8, 0);
    }
}

#[test]
fn bytes_follow_the_documented_layout() {
    let layout = RecordLayout::new(2, 1);
    let t = Transition {
        obs: vec![1.5, -2.0],
        action: vec![0.25],
        reward: 1.0,
        next_obs: vec![3.0, 4.0],
        mask: 0.5,
        stage_epoch: 0x1122_3344_5566_7788,
        actor_id: 0xAABB_CCDD,
        policy_version: 9,
    };
    let mut bytes = vec![0xFF; layout.record_bytes()];
    layout.encode(&t, &mut bytes).unwrap();
    assert_eq!(bytes.len(), 56); // 32 + 4·5 = 52 → 56
    assert_eq!(bytes[0..8], 0x1122_3344_5566_7788u64.to_le_bytes());
    assert_eq!(bytes[8..16], 9u64.to_le_bytes());
    assert_eq!(bytes[16..20], 0xAABB_CCDDu32.to_le_bytes());
    assert_eq!(bytes[20..24], 1.0f32.to_le_bytes());
    assert_eq!(bytes[24..28], 0.5f32.to_le_bytes());
    assert_eq!(bytes[28..32], [0; 4], "header padding is zeroed");
    assert_eq!(bytes[32..36], 1.5f32.to_le_bytes());
    assert_eq!(bytes[36..40], (-2.0f32).to_le_bytes());
    assert_eq!(bytes[40..44], 0.25f32.to_le_bytes());
    assert_eq!(bytes[44..48], 3.0f32.to_le_bytes());
    assert_eq!(bytes[48..52], 4.0f32.to_le_bytes());
    assert_eq!(bytes[52..56], [0; 4], "tail padding is zeroed");
}

#[test]
fn view_reads_fields_and_copies_into_caller_slices() {
    let layout = RecordLayout::new(42, 8);
    let t = transition(layout, 7.0);
    let mut bytes = vec![0; layout.record_bytes()];
    layout.encode(&t, &mut bytes).unwrap();

    let view = layout.view(&bytes).unwrap();
    assert_eq!(view.stage_epoch(), t.stage_epoch);
    assert_eq!(view.policy_version(), t.policy_version);
    assert_eq!(view.actor_id(), 17);
    assert_eq!(view.reward(), 1.0);
    assert_eq!(view.mask(), 0.0);
    let (mut obs, mut action, mut next_obs) = ([0.0; 42], [0.0; 8], [0.0; 42]);
    view.obs_into(&mut obs).unwrap();
    view.action_into(&mut action).unwrap();
    view.next_obs_into(&mut next_obs).unwrap();
    assert_eq!(
        (obs.as_slice(), action.as_slice(), next_obs.as_slice()),
        (&t.obs[..], &t.action[..], &t.next_obs[..])
    );

    let err = view.action_into(&mut [0.0; 7]).unwrap_err();
    assert_eq!(
        err.to_string(),
        "transition action has 7 values, expected action_dim 8"
    );
}

#[test]
fn batches_round_trip_and_view_in_order() {
    let layout = RecordLayout::new(5, 3);
    let batch: Vec<Transition> = (0..4).map(|i| transition(layout, i as f32)).collect();
    let mut bytes = vec![0; 4 * layout.record_bytes()];
    layout.encode_batch(&batch, &mut bytes).unwrap();
    assert_eq!(layout.decode_batch(&bytes).unwrap(), batch);
    let views = layout.view_batch(&bytes).unwrap();
    assert_eq!(views.len(), 4);
    let epochs: Vec<u64> = views.map(|v| v.stage_epoch()).collect();
    assert_eq!(epochs, [3, 4, 5, 6]);
    assert!(layout.decode_batch(&[]).unwrap().is_empty());
}

#[test]
fn wrong_lengths_name_expected_and_actual_bytes_and_dims() {
    let layout = RecordLayout::new(42, 8);
    let t = transition(layout, 0.0);

    let err = layout.encode(&t, &mut [0; 396]).unwrap_err();
    assert_eq!(
        err,
        RecordError::RecordLength {
            expected: 400,
            got: 396,
            obs_dim: 42,
            action_dim: 8
        }
    );
    assert_eq!(
        err.to_string(),
        "transition record is 396 bytes, expected 400 (obs_dim 42, action_dim 8)"
    );
    assert!(matches!(
        layout.decode(&[0; 401]),
        Err(RecordError::RecordLength { got: 401, .. })
    ));

    let err = layout.decode_batch(&[0; 801]).unwrap_err();
    assert_eq!(
        err.to_string(),
        "transition batch of 801 bytes is not a whole number of 400-byte records (obs_dim 42, action_dim 8)"
    );

    let err = layout
        .encode_batch(&[t.clone(), t.clone()], &mut [0; 400])
        .unwrap_err();
    assert_eq!(
        err.to_string(),
        "output buffer is 400 bytes, expected 2 records × 400 = 800 bytes (obs_dim 42, action_dim 8)"
    );

    let mut short = t.clone();
    short.next_obs.pop();
    let err = layout.encode(&short, &mut [0; 400]).unwrap_err();
    assert_eq!(
        err.to_string(),
        "transition next_obs has 41 values, expected obs_dim 42"
    );
}

fn any_transition() -> impl Strategy<Value = (RecordLayout, Transition)> {
    (0usize..64, 0usize..16).prop_flat_map(|(d, a)| {
        let floats = |n| prop::collection::vec(any::<f32>(), n);
        (
            floats(d),
            floats(a),
            floats(d),
            any::<f32>(),
            any::<f32>(),
            any::<u64>(),
            any::<u32>(),
            any::<u64>(),
        )
            .prop_map(
                move |(
                    obs,
                    action,
                    next_obs,
                    reward,
                    mask,
                    stage_epoch,
                    actor_id,
                    policy_version,
                )| {
                    let t = Transition {
                        obs,
                        action,
                        reward,
                        next_obs,
                        mask,
                        stage_epoch,
                        actor_id,
                        policy_version,
                    };
                    (RecordLayout::new(d, a), t)
                },
            )
    })
}

/// A transition's fields as bit patterns, so that NaNs compare too.
type Bits = (Vec<u32>, Vec<u32>, u32, Vec<u32>, u32, u64, u32, u64);

fn bits(t: &Transition) -> Bits {
    let b = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect();
    (
        b(&t.obs),
        b(&t.action),
        t.reward.to_bits(),
        b(&t.next_obs),
        t.mask.to_bits(),
        t.stage_epoch,
        t.actor_id,
        t.policy_version,
    )
}

proptest! {
    #[test]
    fn any_transition_round_trips_bit_for_bit((layout, t) in any_transition()) {
        let mut bytes = vec![0xA5; layout.record_bytes()];
        layout.encode(&t, &mut bytes).unwrap();
        prop_assert_eq!(bits(&layout.decode(&bytes).unwrap()), bits(&t));
        let view = layout.view(&bytes).unwrap();
        prop_assert_eq!(view.actor_id(), t.actor_id);
        prop_assert_eq!(bits(&view.to_transition()), bits(&t));
    }

    #[test]
    fn any_batch_round_trips((layout, t) in any_transition(), n in 0usize..6) {
        let batch: Vec<Transition> =
            (0..n).map(|i| Transition { actor_id: i as u32, ..t.clone() }).collect();
        let mut bytes = vec![0; n * layout.record_bytes()];
        layout.encode_batch(&batch, &mut bytes).unwrap();
        let decoded = layout.decode_batch(&bytes).unwrap();
        let expected: Vec<Bits> = batch.iter().map(bits).collect();
        prop_assert_eq!(decoded.iter().map(bits).collect::<Vec<_>>(), expected);
    }
}
