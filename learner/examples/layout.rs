use std::time::Instant;
use tch::{Device, Kind, Tensor};

fn time<F: FnMut()>(name: &str, n: usize, mut f: F) {
    f();
    let mut best = f64::MAX;
    for _ in 0..3 {
        let s = Instant::now();
        for _ in 0..n {
            f();
        }
        best = best.min(s.elapsed().as_secs_f64() / n as f64 * 1e3);
    }
    println!("{name:40} {best:8.3} ms");
}
fn p(s: &[i64]) -> Tensor {
    (Tensor::randn(s, (Kind::Float, Device::Cpu)) * 0.05).set_requires_grad(true)
}

fn main() {
    let threads: i32 = std::env::var("T").map(|t| t.parse().unwrap()).unwrap_or(1);
    rfcl_learner::runtime::configure_cpu(threads);
    let (e, b, h, inp) = (10i64, 256i64, 256i64, 50i64);
    let x = Tensor::randn([b, inp], (Kind::Float, Device::Cpu));
    let w1 = p(&[inp, e * h]);
    let b1 = p(&[e * h]);
    let w1s = p(&[e, inp, h]);
    let b1s = p(&[e, 1, h]);
    let ws: Vec<Tensor> = (0..2).map(|_| p(&[e, h, h])).collect();
    let bs: Vec<Tensor> = (0..2).map(|_| p(&[e, 1, h])).collect();
    let gs: Vec<Tensor> = (0..3).map(|_| p(&[e, 1, h])).collect();
    let be: Vec<Tensor> = (0..3).map(|_| p(&[e, 1, h])).collect();
    let g1 = p(&[e * h]);
    let be1 = p(&[e * h]);
    let wo = p(&[e, h, 1]);
    let bo = p(&[e, 1, 1]);
    let y = Tensor::randn([b], (Kind::Float, Device::Cpu));
    let ln = |t: &Tensor, i: usize| -> Tensor {
        let n = t.layer_norm([h], None::<Tensor>, None::<Tensor>, 1e-6, false);
        be[i].addcmul(&n, &gs[i]).relu()
    };
    let ln_inplace = |t: &Tensor, i: usize| -> Tensor {
        let n = t.layer_norm([h], None::<Tensor>, None::<Tensor>, 1e-6, false);
        be[i].addcmul(&n, &gs[i]).relu_()
    };
    let nln = |t: &Tensor, _i: usize| -> Tensor { t.relu() };
    let tail2 = |mut hh: Tensor, f: &dyn Fn(&Tensor, usize) -> Tensor| -> Tensor {
        for i in 0..2 {
            hh = f(&bs[i].baddbmm(&hh, &ws[i], 1.0, 1.0), i + 1);
        }
        bo.baddbmm(&hh, &wo, 1.0, 1.0).squeeze_dim(-1)
    };
    let vf = || {
        tail2(
            ln_inplace(
                &b1s.baddbmm(&x.expand([e, b, inp], false), &w1s, 1.0, 1.0),
                0,
            ),
            &ln_inplace,
        )
    };
    let vg = || {
        tail2(
            nln(
                &b1s.baddbmm(&x.expand([e, b, inp], false), &w1s, 1.0, 1.0),
                0,
            ),
            &nln,
        )
    };
    let tail = |mut hh: Tensor| -> Tensor {
        for i in 0..2 {
            hh = ln(&bs[i].baddbmm(&hh, &ws[i], 1.0, 1.0), i + 1);
        }
        bo.baddbmm(&hh, &wo, 1.0, 1.0).squeeze_dim(-1)
    };
    let va = || tail(ln(&b1.addmm(&x, &w1).view([b, e, h]).transpose(0, 1), 0));
    let vb = || {
        tail(ln(
            &b1.addmm(&x, &w1)
                .view([b, e, h])
                .transpose(0, 1)
                .contiguous(),
            0,
        ))
    };
    let vc = || {
        tail(ln(
            &b1s.baddbmm(&x.expand([e, b, inp], false), &w1s, 1.0, 1.0),
            0,
        ))
    };
    let vd = || {
        tail(
            b1.addmm(&x, &w1)
                .group_norm(e, Some(&g1), Some(&be1), 1e-6, false)
                .relu()
                .view([b, e, h])
                .transpose(0, 1),
        )
    };
    let ve = || {
        tail(
            b1.addmm(&x, &w1)
                .group_norm(e, Some(&g1), Some(&be1), 1e-6, false)
                .relu()
                .view([b, e, h])
                .transpose(0, 1)
                .contiguous(),
        )
    };
    let params: Vec<&Tensor> = vec![
        &ws[0], &ws[1], &bs[0], &bs[1], &gs[1], &gs[2], &be[1], &be[2], &wo, &bo,
    ];
    if std::env::var("ONLY_A").is_ok() {
        let mut all = params.clone();
        all.extend(vec![&w1, &b1, &gs[0], &be[0]]);
        for _ in 0..300 {
            let q = va();
            let l = (q - y.unsqueeze(0)).square().mean(None);
            let _ = Tensor::run_backward(&[l], &all, false, false);
        }
        return;
    }
    if std::env::var("AB").is_ok() {
        let mut best = [f64::MAX; 3];
        for _ in 0..6 {
            for (k, (f, extra)) in [
                (&va as &dyn Fn() -> Tensor, vec![&w1, &b1, &gs[0], &be[0]]),
                (&vb, vec![&w1, &b1, &gs[0], &be[0]]),
                (&vc, vec![&w1s, &b1s, &gs[0], &be[0]]),
            ]
            .into_iter()
            .enumerate()
            {
                let mut all = params.clone();
                all.extend(extra);
                let s = Instant::now();
                for _ in 0..10 {
                    let q = f();
                    let l = (q - y.unsqueeze(0)).square().mean(None);
                    let _ = Tensor::run_backward(&[l], &all, false, false);
                }
                best[k] = best[k].min(s.elapsed().as_secs_f64() / 10.0 * 1e3);
            }
        }
        println!(
            "a strided {:.2}  b contiguous {:.2}  c expand {:.2}",
            best[0], best[1], best[2]
        );
        return;
    }
    for (name, f, extra) in [
        (
            "a strided",
            &va as &dyn Fn() -> Tensor,
            vec![&w1, &b1, &gs[0], &be[0]],
        ),
        ("b contiguous", &vb, vec![&w1, &b1, &gs[0], &be[0]]),
        ("c expand bmm", &vc, vec![&w1s, &b1s, &gs[0], &be[0]]),
        ("f expand + relu_", &vf, vec![&w1s, &b1s, &gs[0], &be[0]]),
        ("g expand no LN", &vg, vec![&w1s, &b1s]),
        ("d groupnorm strided", &vd, vec![&w1, &b1, &g1, &be1]),
        ("e groupnorm contiguous", &ve, vec![&w1, &b1, &g1, &be1]),
    ] {
        let mut all = params.clone();
        all.extend(extra);
        time(&format!("{name} fwd nograd"), 10, || {
            let _ = tch::no_grad(|| f());
        });
        time(&format!("{name} fwd+bwd"), 10, || {
            let q = f();
            let l = (q - y.unsqueeze(0)).square().mean(None);
            let _ = Tensor::run_backward(&[l], &all, false, false);
        });
    }
    // elementwise costs
    let t = Tensor::randn([e, b, h], (Kind::Float, Device::Cpu));
    time("layer_norm", 20, || {
        let _ = t.layer_norm([h], None::<Tensor>, None::<Tensor>, 1e-6, false);
    });
    time("addcmul", 20, || {
        let _ = be[0].addcmul(&t, &gs[0]);
    });
    time("relu", 20, || {
        let _ = t.relu();
    });
    time("copy", 20, || {
        let _ = t.copy();
    });
    time("bmm 10x256x256x256", 20, || {
        let _ = t.bmm(&ws[0]);
    });
    let tb = t.to_kind(Kind::BFloat16);
    let wb = ws[0].to_kind(Kind::BFloat16);
    time("bmm bf16", 20, || {
        let _ = tb.bmm(&wb);
    });
    time("to bf16", 20, || {
        let _ = t.to_kind(Kind::BFloat16);
    });
}
