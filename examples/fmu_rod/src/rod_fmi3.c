/* FMI 3.0 interface of the example rod (Model Exchange and Co-Simulation in one binary).
 * Physics in rod_model.h. The temperatures are one array variable T (and der(T)) of N_NODES
 * elements; value references are this file's (FMI 3.0 has one value-reference space).
 * Built by ../build_fmu.py against the FMI 3.0 headers fmpy ships. */
#include <stdio.h>
#include <stdlib.h>
#include "fmi3Functions.h"
#include "rod_model.h"

#ifndef MODEL_GUID
#define MODEL_GUID "{sep-rod}"
#endif

enum { VR3_TIME = 0, VR3_T = 1, VR3_DER = 2, VR3_U = 3, VR3_QLEFT = VR3_U + N_HEATERS,
       VR3_Y = VR3_QLEFT + 1, VR3_P = VR3_Y + N_SENSORS, VR3_NSUB = VR3_P + N_PARAMS };

typedef struct {
    RodState s;
    RodDerived d;
    double dT[N_NODES];
    int dT_valid;
    fmi3InstanceEnvironment env;
    fmi3LogMessageCallback log;
} Instance;

static fmi3Status fail(fmi3Instance c, const char *msg) {
    Instance *i = (Instance *)c;
    if (i && i->log) i->log(i->env, fmi3Error, "error", msg);
    return fmi3Error;
}

static fmi3Instance create(fmi3String token, fmi3InstanceEnvironment env, fmi3LogMessageCallback log) {
    if (!token || strcmp(token, MODEL_GUID) != 0) return NULL;
    Instance *c = (Instance *)calloc(1, sizeof(Instance));
    if (!c) return NULL;
    c->env = env;
    c->log = log;
    rod_defaults(&c->s);
    rod_derive(&c->s, &c->d);
    rod_init_states(&c->s);
    return c;
}

const char *fmi3GetVersion(void) { return fmi3Version; }

fmi3Status fmi3SetDebugLogging(fmi3Instance c, fmi3Boolean on, size_t n, const fmi3String cat[]) {
    (void)c; (void)on; (void)n; (void)cat; return fmi3OK;
}

fmi3Instance fmi3InstantiateModelExchange(fmi3String name, fmi3String token, fmi3String res, fmi3Boolean visible,
                                          fmi3Boolean logging, fmi3InstanceEnvironment env,
                                          fmi3LogMessageCallback log) {
    (void)name; (void)res; (void)visible; (void)logging;
    return create(token, env, log);
}

fmi3Instance fmi3InstantiateCoSimulation(fmi3String name, fmi3String token, fmi3String res, fmi3Boolean visible,
                                         fmi3Boolean logging, fmi3Boolean eventModeUsed, fmi3Boolean earlyReturn,
                                         const fmi3ValueReference req[], size_t nreq,
                                         fmi3InstanceEnvironment env, fmi3LogMessageCallback log,
                                         fmi3IntermediateUpdateCallback upd) {
    (void)name; (void)res; (void)visible; (void)logging; (void)earlyReturn; (void)req; (void)nreq; (void)upd;
    if (eventModeUsed) return NULL;
    return create(token, env, log);
}

fmi3Instance fmi3InstantiateScheduledExecution(fmi3String name, fmi3String token, fmi3String res,
                                               fmi3Boolean visible, fmi3Boolean logging,
                                               fmi3InstanceEnvironment env, fmi3LogMessageCallback log,
                                               fmi3ClockUpdateCallback cu, fmi3LockPreemptionCallback lp,
                                               fmi3UnlockPreemptionCallback up) {
    (void)name; (void)token; (void)res; (void)visible; (void)logging; (void)env; (void)log; (void)cu;
    (void)lp; (void)up;
    return NULL;
}

void fmi3FreeInstance(fmi3Instance c) { free(c); }

fmi3Status fmi3EnterInitializationMode(fmi3Instance c, fmi3Boolean tolDef, fmi3Float64 tol, fmi3Float64 start,
                                       fmi3Boolean stopDef, fmi3Float64 stop) {
    (void)tolDef; (void)tol; (void)stopDef; (void)stop;
    ((Instance *)c)->s.time = start;
    return fmi3OK;
}

fmi3Status fmi3ExitInitializationMode(fmi3Instance c) {
    Instance *i = (Instance *)c;
    if (i->s.n_substeps < 1) return fail(c, "n_substeps must be >= 1");
    if (!(i->s.p[P_LENGTH] > 0) || !(i->s.p[P_SIGMA] > 0) || !(i->s.p[P_TSCALE] > 0))
        return fail(c, "length, heater_sigma and t_scale must be > 0");
    rod_derive(&i->s, &i->d);
    rod_init_states(&i->s);
    i->s.initialized = 1;
    i->dT_valid = 0;
    return fmi3OK;
}

fmi3Status fmi3EnterEventMode(fmi3Instance c) { (void)c; return fmi3OK; }
fmi3Status fmi3Terminate(fmi3Instance c) { (void)c; return fmi3OK; }

fmi3Status fmi3Reset(fmi3Instance c) {
    Instance *i = (Instance *)c;
    rod_defaults(&i->s);
    rod_derive(&i->s, &i->d);
    rod_init_states(&i->s);
    i->dT_valid = 0;
    return fmi3OK;
}

/* ---------------------------------------------------------------- Float64 and Int32 */
fmi3Status fmi3GetFloat64(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, fmi3Float64 v[], size_t nv) {
    Instance *i = (Instance *)c;
    size_t k = 0;
    for (size_t r = 0; r < nvr; r++) {
        const fmi3ValueReference ref = vr[r];
        if (ref == VR3_T || ref == VR3_DER) {
            if (k + N_NODES > nv) return fail(c, "fmi3GetFloat64: too few values");
            if (ref == VR3_DER && !i->dT_valid) { rod_rhs(&i->s, &i->d, i->s.T, i->dT); i->dT_valid = 1; }
            memcpy(v + k, ref == VR3_T ? i->s.T : i->dT, sizeof(double) * N_NODES);
            k += N_NODES;
            continue;
        }
        if (k >= nv) return fail(c, "fmi3GetFloat64: too few values");
        if (ref == VR3_TIME) v[k] = i->s.time;
        else if (ref >= VR3_U && ref < VR3_QLEFT) v[k] = i->s.u[ref - VR3_U];
        else if (ref == VR3_QLEFT) v[k] = i->s.q_left;
        else if (ref >= VR3_Y && ref < VR3_P) v[k] = i->s.T[i->d.sensor[ref - VR3_Y]];
        else if (ref >= VR3_P && ref < VR3_NSUB) v[k] = i->s.p[ref - VR3_P];
        else return fail(c, "fmi3GetFloat64: unknown value reference");
        k++;
    }
    return k == nv ? fmi3OK : fail(c, "fmi3GetFloat64: wrong number of values");
}

fmi3Status fmi3SetFloat64(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, const fmi3Float64 v[],
                          size_t nv) {
    Instance *i = (Instance *)c;
    if (nv != nvr) return fail(c, "fmi3SetFloat64: only scalars can be set");
    for (size_t r = 0; r < nvr; r++) {
        const fmi3ValueReference ref = vr[r];
        if (ref >= VR3_U && ref < VR3_QLEFT) i->s.u[ref - VR3_U] = v[r];
        else if (ref == VR3_QLEFT) i->s.q_left = v[r];
        else if (ref >= VR3_P && ref < VR3_NSUB && !i->s.initialized) i->s.p[ref - VR3_P] = v[r];
        else return fail(c, "fmi3SetFloat64: not settable now");
    }
    i->dT_valid = 0;
    return fmi3OK;
}

fmi3Status fmi3GetInt32(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, fmi3Int32 v[], size_t nv) {
    if (nv != nvr) return fail(c, "fmi3GetInt32: wrong number of values");
    for (size_t r = 0; r < nvr; r++) {
        if (vr[r] != VR3_NSUB) return fail(c, "fmi3GetInt32: unknown value reference");
        v[r] = ((Instance *)c)->s.n_substeps;
    }
    return fmi3OK;
}

fmi3Status fmi3SetInt32(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, const fmi3Int32 v[], size_t nv) {
    Instance *i = (Instance *)c;
    if (nv != nvr) return fail(c, "fmi3SetInt32: wrong number of values");
    for (size_t r = 0; r < nvr; r++) {
        if (vr[r] != VR3_NSUB || i->s.initialized) return fail(c, "fmi3SetInt32: not settable now");
        i->s.n_substeps = v[r];
    }
    return fmi3OK;
}

/* the other value types: the rod has none */
#define NO_GET(NAME, T) \
    fmi3Status NAME(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, T v[], size_t nv) { \
        (void)vr; (void)v; (void)nv; return nvr ? fail(c, #NAME ": no such variables") : fmi3OK; }
#define NO_SET(NAME, T) \
    fmi3Status NAME(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, const T v[], size_t nv) { \
        (void)vr; (void)v; (void)nv; return nvr ? fail(c, #NAME ": no such variables") : fmi3OK; }
NO_GET(fmi3GetFloat32, fmi3Float32) NO_GET(fmi3GetInt8, fmi3Int8) NO_GET(fmi3GetUInt8, fmi3UInt8)
NO_GET(fmi3GetInt16, fmi3Int16) NO_GET(fmi3GetUInt16, fmi3UInt16) NO_GET(fmi3GetUInt32, fmi3UInt32)
NO_GET(fmi3GetInt64, fmi3Int64) NO_GET(fmi3GetUInt64, fmi3UInt64) NO_GET(fmi3GetBoolean, fmi3Boolean)
NO_GET(fmi3GetString, fmi3String)
NO_SET(fmi3SetFloat32, fmi3Float32) NO_SET(fmi3SetInt8, fmi3Int8) NO_SET(fmi3SetUInt8, fmi3UInt8)
NO_SET(fmi3SetInt16, fmi3Int16) NO_SET(fmi3SetUInt16, fmi3UInt16) NO_SET(fmi3SetUInt32, fmi3UInt32)
NO_SET(fmi3SetInt64, fmi3Int64) NO_SET(fmi3SetUInt64, fmi3UInt64) NO_SET(fmi3SetBoolean, fmi3Boolean)
NO_SET(fmi3SetString, fmi3String)

fmi3Status fmi3GetBinary(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, size_t sizes[],
                         fmi3Binary v[], size_t nv) {
    (void)vr; (void)sizes; (void)v; (void)nv; return nvr ? fail(c, "no Binary variables") : fmi3OK;
}
fmi3Status fmi3SetBinary(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, const size_t sizes[],
                         const fmi3Binary v[], size_t nv) {
    (void)vr; (void)sizes; (void)v; (void)nv; return nvr ? fail(c, "no Binary variables") : fmi3OK;
}
fmi3Status fmi3GetClock(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, fmi3Clock v[]) {
    (void)vr; (void)v; return nvr ? fail(c, "no clocks") : fmi3OK;
}
fmi3Status fmi3SetClock(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, const fmi3Clock v[]) {
    (void)vr; (void)v; return nvr ? fail(c, "no clocks") : fmi3OK;
}

fmi3Status fmi3GetNumberOfVariableDependencies(fmi3Instance c, fmi3ValueReference vr, size_t *n) {
    (void)vr; (void)n; return fail(c, "variable dependencies are not provided");
}
fmi3Status fmi3GetVariableDependencies(fmi3Instance c, fmi3ValueReference dep, size_t ei[], fmi3ValueReference ind[],
                                       size_t eii[], fmi3DependencyKind kinds[], size_t n) {
    (void)dep; (void)ei; (void)ind; (void)eii; (void)kinds; (void)n;
    return fail(c, "variable dependencies are not provided");
}

/* ---------------------------------------------------------------- FMU state */
fmi3Status fmi3GetFMUState(fmi3Instance c, fmi3FMUState *state) {
    if (!*state) *state = malloc(sizeof(RodState));
    if (!*state) return fail(c, "out of memory");
    memcpy(*state, &((Instance *)c)->s, sizeof(RodState));
    return fmi3OK;
}

fmi3Status fmi3SetFMUState(fmi3Instance c, fmi3FMUState state) {
    Instance *i = (Instance *)c;
    if (!state) return fail(c, "fmi3SetFMUState: no state");
    memcpy(&i->s, state, sizeof(RodState));
    rod_derive(&i->s, &i->d);
    i->dT_valid = 0;
    return fmi3OK;
}

fmi3Status fmi3FreeFMUState(fmi3Instance c, fmi3FMUState *state) {
    (void)c;
    if (state && *state) { free(*state); *state = NULL; }
    return fmi3OK;
}

fmi3Status fmi3SerializedFMUStateSize(fmi3Instance c, fmi3FMUState state, size_t *size) {
    (void)c; (void)state; *size = sizeof(RodState); return fmi3OK;
}

fmi3Status fmi3SerializeFMUState(fmi3Instance c, fmi3FMUState state, fmi3Byte bytes[], size_t size) {
    if (size != sizeof(RodState)) return fail(c, "fmi3SerializeFMUState: wrong size");
    memcpy(bytes, state, sizeof(RodState));
    return fmi3OK;
}

fmi3Status fmi3DeserializeFMUState(fmi3Instance c, const fmi3Byte bytes[], size_t size, fmi3FMUState *state) {
    if (size != sizeof(RodState)) return fail(c, "fmi3DeserializeFMUState: wrong size");
    if (!*state) *state = malloc(sizeof(RodState));
    if (!*state) return fail(c, "out of memory");
    memcpy(*state, bytes, sizeof(RodState));
    return fmi3OK;
}

fmi3Status fmi3GetDirectionalDerivative(fmi3Instance c, const fmi3ValueReference u[], size_t nu,
                                        const fmi3ValueReference k[], size_t nk, const fmi3Float64 seed[],
                                        size_t ns, fmi3Float64 sens[], size_t nsens) {
    (void)u; (void)nu; (void)k; (void)nk; (void)seed; (void)ns; (void)sens; (void)nsens;
    return fail(c, "directional derivatives are not provided");
}
fmi3Status fmi3GetAdjointDerivative(fmi3Instance c, const fmi3ValueReference u[], size_t nu,
                                    const fmi3ValueReference k[], size_t nk, const fmi3Float64 seed[],
                                    size_t ns, fmi3Float64 sens[], size_t nsens) {
    (void)u; (void)nu; (void)k; (void)nk; (void)seed; (void)ns; (void)sens; (void)nsens;
    return fail(c, "adjoint derivatives are not provided");
}

/* ---------------------------------------------------------------- clocks, configuration: none */
fmi3Status fmi3EnterConfigurationMode(fmi3Instance c) { return fail(c, "no structural parameters"); }
fmi3Status fmi3ExitConfigurationMode(fmi3Instance c) { return fail(c, "no structural parameters"); }
fmi3Status fmi3GetIntervalDecimal(fmi3Instance c, const fmi3ValueReference vr[], size_t n, fmi3Float64 iv[],
                                  fmi3IntervalQualifier q[]) {
    (void)vr; (void)n; (void)iv; (void)q; return fail(c, "no clocks");
}
fmi3Status fmi3GetIntervalFraction(fmi3Instance c, const fmi3ValueReference vr[], size_t n, fmi3UInt64 cnt[],
                                   fmi3UInt64 res[], fmi3IntervalQualifier q[]) {
    (void)vr; (void)n; (void)cnt; (void)res; (void)q; return fail(c, "no clocks");
}
fmi3Status fmi3GetShiftDecimal(fmi3Instance c, const fmi3ValueReference vr[], size_t n, fmi3Float64 s[]) {
    (void)vr; (void)n; (void)s; return fail(c, "no clocks");
}
fmi3Status fmi3GetShiftFraction(fmi3Instance c, const fmi3ValueReference vr[], size_t n, fmi3UInt64 cnt[],
                                fmi3UInt64 res[]) {
    (void)vr; (void)n; (void)cnt; (void)res; return fail(c, "no clocks");
}
fmi3Status fmi3SetIntervalDecimal(fmi3Instance c, const fmi3ValueReference vr[], size_t n, const fmi3Float64 iv[]) {
    (void)vr; (void)n; (void)iv; return fail(c, "no clocks");
}
fmi3Status fmi3SetIntervalFraction(fmi3Instance c, const fmi3ValueReference vr[], size_t n, const fmi3UInt64 cnt[],
                                   const fmi3UInt64 res[]) {
    (void)vr; (void)n; (void)cnt; (void)res; return fail(c, "no clocks");
}
fmi3Status fmi3SetShiftDecimal(fmi3Instance c, const fmi3ValueReference vr[], size_t n, const fmi3Float64 s[]) {
    (void)vr; (void)n; (void)s; return fail(c, "no clocks");
}
fmi3Status fmi3SetShiftFraction(fmi3Instance c, const fmi3ValueReference vr[], size_t n, const fmi3UInt64 cnt[],
                                const fmi3UInt64 res[]) {
    (void)vr; (void)n; (void)cnt; (void)res; return fail(c, "no clocks");
}
fmi3Status fmi3EvaluateDiscreteStates(fmi3Instance c) { (void)c; return fmi3OK; }
fmi3Status fmi3ActivateModelPartition(fmi3Instance c, fmi3ValueReference clk, fmi3Float64 t) {
    (void)clk; (void)t; return fail(c, "no model partitions");
}

/* ---------------------------------------------------------------- Model Exchange */
fmi3Status fmi3UpdateDiscreteStates(fmi3Instance c, fmi3Boolean *needUpdate, fmi3Boolean *term,
                                    fmi3Boolean *nominalsChanged, fmi3Boolean *valuesChanged,
                                    fmi3Boolean *nextDefined, fmi3Float64 *next) {
    (void)c;
    *needUpdate = *term = *nominalsChanged = *valuesChanged = *nextDefined = false;
    *next = 0.0;
    return fmi3OK;
}

fmi3Status fmi3EnterContinuousTimeMode(fmi3Instance c) { (void)c; return fmi3OK; }

fmi3Status fmi3CompletedIntegratorStep(fmi3Instance c, fmi3Boolean noSet, fmi3Boolean *enter, fmi3Boolean *term) {
    (void)c; (void)noSet; *enter = false; *term = false; return fmi3OK;
}

fmi3Status fmi3SetTime(fmi3Instance c, fmi3Float64 t) { ((Instance *)c)->s.time = t; return fmi3OK; }

fmi3Status fmi3SetContinuousStates(fmi3Instance c, const fmi3Float64 x[], size_t nx) {
    Instance *i = (Instance *)c;
    if (nx != N_NODES) return fail(c, "fmi3SetContinuousStates: wrong number of states");
    memcpy(i->s.T, x, sizeof(double) * N_NODES);
    i->dT_valid = 0;
    return fmi3OK;
}

fmi3Status fmi3GetContinuousStateDerivatives(fmi3Instance c, fmi3Float64 dx[], size_t nx) {
    Instance *i = (Instance *)c;
    if (nx != N_NODES) return fail(c, "fmi3GetContinuousStateDerivatives: wrong number of states");
    rod_rhs(&i->s, &i->d, i->s.T, dx);
    return fmi3OK;
}

fmi3Status fmi3GetEventIndicators(fmi3Instance c, fmi3Float64 z[], size_t nz) {
    (void)z; return nz ? fail(c, "no event indicators") : fmi3OK;
}

fmi3Status fmi3GetContinuousStates(fmi3Instance c, fmi3Float64 x[], size_t nx) {
    if (nx != N_NODES) return fail(c, "fmi3GetContinuousStates: wrong number of states");
    memcpy(x, ((Instance *)c)->s.T, sizeof(double) * N_NODES);
    return fmi3OK;
}

fmi3Status fmi3GetNominalsOfContinuousStates(fmi3Instance c, fmi3Float64 x[], size_t nx) {
    (void)c; for (size_t k = 0; k < nx; k++) x[k] = 100.0; return fmi3OK;
}

fmi3Status fmi3GetNumberOfEventIndicators(fmi3Instance c, size_t *n) { (void)c; *n = 0; return fmi3OK; }
fmi3Status fmi3GetNumberOfContinuousStates(fmi3Instance c, size_t *n) { (void)c; *n = N_NODES; return fmi3OK; }

/* ---------------------------------------------------------------- Co-Simulation */
fmi3Status fmi3EnterStepMode(fmi3Instance c) { (void)c; return fmi3OK; }

fmi3Status fmi3GetOutputDerivatives(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, const fmi3Int32 o[],
                                    fmi3Float64 v[], size_t nv) {
    (void)vr; (void)nvr; (void)o; (void)v; (void)nv; return fail(c, "output derivatives are not provided");
}

fmi3Status fmi3DoStep(fmi3Instance c, fmi3Float64 t, fmi3Float64 h, fmi3Boolean noSet, fmi3Boolean *event,
                      fmi3Boolean *term, fmi3Boolean *early, fmi3Float64 *last) {
    Instance *i = (Instance *)c;
    (void)noSet;
    *event = false; *term = false; *early = false;
    if (fabs(t - i->s.time) > 1e-9 * (1.0 + fabs(t))) return fail(c, "fmi3DoStep: time differs from the FMU's");
    if (!(h > 0)) return fail(c, "fmi3DoStep: step size must be > 0");
    rod_rk4(&i->s, &i->d, h);
    i->dT_valid = 0;
    *last = i->s.time;
    return fmi3OK;
}
