/* The physics of the example rod FMU, shared by its FMI 2.0 and FMI 3.0 interfaces.
 *
 * A rod of length L, insulated at x = 0 except for an inflow heat flux q_left, held at
 * t_right at x = L, cooled towards t_amb, heated by N_HEATERS Gaussian heaters:
 *
 *   dT/dt = d/dx (K(T) dT/dx) - eta (T - t_amb) + sum_j b_j(x) u_j,
 *   K(T)  = k0 (1 + beta (T - t_ref) / t_scale),
 *   b_j(x) = exp(-(x - c_j L)^2 / (2 (s L)^2)) / (s L sqrt(2 pi)),
 *
 * on N_NODES cells of width h = L / N_NODES (centres x_i = (i + 1/2) h). Flux form with face
 * conductivities K_{i+1/2} = (K_i + K_{i+1}) / 2; the right face sits h/2 from the last centre:
 *
 *   dT_i/dt = (F_{i+1/2} - F_{i-1/2}) / h - eta (T_i - t_amb) + sum_j b_j(x_i) u_j,
 *   F_{i+1/2} = K_{i+1/2} (T_{i+1} - T_i) / h,   F_{-1/2} = -q_left,
 *   F_{N-1/2} = (K_{N-1} + K(t_right)) / 2 (t_right - T_{N-1}) / (h / 2).
 *
 * Sensors read the cell containing sensor_position_j L. Co-Simulation integrates with classical
 * RK4, n_substeps steps per communication step, inputs held: the same arithmetic, in the same
 * order, as sep's Model Exchange stepping (sep_plant.plants.fmu.exchange). C99, no globals.
 */
#ifndef ROD_MODEL_H
#define ROD_MODEL_H

#include <math.h>
#include <string.h>

#ifndef N_NODES
#define N_NODES 50
#endif
#define N_HEATERS 3
#define N_SENSORS 3
#define ROD_PI 3.14159265358979323846

/* value references (FMI 2.0: one space per type; FMI 3.0: one space) */
enum {
    VR_T = 0,                                 /* T[1] .. T[N]           (states)      */
    VR_DER = VR_T + N_NODES,                  /* der(T[1]) .. der(T[N]) (derivatives) */
    VR_U = VR_DER + N_NODES,                  /* heater_1 .. heater_3   (inputs)      */
    VR_QLEFT = VR_U + N_HEATERS,              /* q_left                 (input)       */
    VR_Y = VR_QLEFT + 1,                      /* sensor_1 .. sensor_3   (outputs)     */
    VR_P = VR_Y + N_SENSORS,                  /* the Real parameters below            */
    VR_NSUB = VR_P + 10 + N_HEATERS + N_SENSORS,  /* n_substeps (Integer parameter)   */
    VR_END
};

/* Real parameters, in value-reference order from VR_P */
enum { P_LENGTH, P_K0, P_BETA, P_TREF, P_TSCALE, P_ETA, P_TAMB, P_TRIGHT, P_TINIT, P_SIGMA,
       P_CENTER, P_SENSOR = P_CENTER + N_HEATERS, N_PARAMS = P_SENSOR + N_SENSORS };

/* what an FMU state holds (serialized as raw bytes) */
typedef struct {
    double time;
    double T[N_NODES];
    double u[N_HEATERS];
    double q_left;
    double p[N_PARAMS];
    int n_substeps;
    int initialized;
} RodState;

/* quantities derived from the parameters (recomputed, never serialized) */
typedef struct {
    double h;
    double B[N_NODES][N_HEATERS];
    int sensor[N_SENSORS];
} RodDerived;

static void rod_defaults(RodState *s) {
    static const double defaults[N_PARAMS] = {
        1.0, 0.002, 0.5, 100.0, 50.0, 0.002, 70.0, 150.0, 100.0, 0.05,
        0.2, 0.5, 0.8,                        /* heater centres (fractions of L) */
        0.3, 0.55, 0.9                        /* sensor positions (fractions of L) */
    };
    memset(s, 0, sizeof(*s));
    memcpy(s->p, defaults, sizeof(defaults));
    s->n_substeps = 4;
}

static void rod_derive(const RodState *s, RodDerived *d) {
    const double L = s->p[P_LENGTH], sig = s->p[P_SIGMA] * L;
    d->h = L / N_NODES;
    for (int i = 0; i < N_NODES; i++) {
        const double x = (i + 0.5) * d->h;
        for (int j = 0; j < N_HEATERS; j++) {
            const double z = (x - s->p[P_CENTER + j] * L) / sig;
            d->B[i][j] = exp(-0.5 * z * z) / (sig * sqrt(2.0 * ROD_PI));
        }
    }
    for (int j = 0; j < N_SENSORS; j++) {
        int k = (int)floor(s->p[P_SENSOR + j] * N_NODES);
        d->sensor[j] = k < 0 ? 0 : (k > N_NODES - 1 ? N_NODES - 1 : k);
    }
}

static void rod_init_states(RodState *s) {
    for (int i = 0; i < N_NODES; i++) s->T[i] = s->p[P_TINIT];
}

static double rod_conductivity(const RodState *s, double T) {
    return s->p[P_K0] * (1.0 + s->p[P_BETA] * (T - s->p[P_TREF]) / s->p[P_TSCALE]);
}

/* dT/dt at the states T (not necessarily s->T) under the inputs held in s */
static void rod_rhs(const RodState *s, const RodDerived *d, const double *T, double *dT) {
    const double h = d->h, eta = s->p[P_ETA], t_amb = s->p[P_TAMB], t_right = s->p[P_TRIGHT];
    double K[N_NODES];
    for (int i = 0; i < N_NODES; i++) K[i] = rod_conductivity(s, T[i]);
    double f_left = -s->q_left;                                   /* F_{-1/2} */
    for (int i = 0; i < N_NODES; i++) {
        double f_right;
        if (i < N_NODES - 1)
            f_right = 0.5 * (K[i] + K[i + 1]) * (T[i + 1] - T[i]) / h;
        else
            f_right = 0.5 * (K[i] + rod_conductivity(s, t_right)) * (t_right - T[i]) / (0.5 * h);
        double src = 0.0;
        for (int j = 0; j < N_HEATERS; j++) src += d->B[i][j] * s->u[j];
        dT[i] = (f_right - f_left) / h - eta * (T[i] - t_amb) + src;
        f_left = f_right;
    }
}

/* classical RK4 over dt in n_substeps steps, inputs held */
static void rod_rk4(RodState *s, const RodDerived *d, double dt) {
    const int m = s->n_substeps;
    const double tau = dt / m;
    double k1[N_NODES], k2[N_NODES], k3[N_NODES], k4[N_NODES], y[N_NODES];
    double *T = s->T;
    for (int step = 0; step < m; step++) {
        rod_rhs(s, d, T, k1);
        for (int i = 0; i < N_NODES; i++) y[i] = T[i] + (0.5 * tau) * k1[i];
        rod_rhs(s, d, y, k2);
        for (int i = 0; i < N_NODES; i++) y[i] = T[i] + (0.5 * tau) * k2[i];
        rod_rhs(s, d, y, k3);
        for (int i = 0; i < N_NODES; i++) y[i] = T[i] + tau * k3[i];
        rod_rhs(s, d, y, k4);
        for (int i = 0; i < N_NODES; i++)
            T[i] = T[i] + (tau / 6.0) * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]);
    }
    s->time += dt;
}

/* a Real variable by value reference (derivatives need dT, computed by the caller) */
static int rod_get_real(const RodState *s, const RodDerived *d, const double *dT, unsigned vr, double *v) {
    if (vr < VR_DER) *v = s->T[vr - VR_T];
    else if (vr < VR_U) *v = dT[vr - VR_DER];
    else if (vr < VR_QLEFT) *v = s->u[vr - VR_U];
    else if (vr == VR_QLEFT) *v = s->q_left;
    else if (vr < VR_P) *v = s->T[d->sensor[vr - VR_Y]];
    else if (vr < VR_NSUB) *v = s->p[vr - VR_P];
    else return 0;
    return 1;
}

/* set a Real variable: inputs any time, parameters before initialization only */
static int rod_set_real(RodState *s, unsigned vr, double v) {
    if (vr >= VR_U && vr < VR_QLEFT) s->u[vr - VR_U] = v;
    else if (vr == VR_QLEFT) s->q_left = v;
    else if (vr >= VR_P && vr < VR_NSUB && !s->initialized) s->p[vr - VR_P] = v;
    else return 0;
    return 1;
}

#endif
