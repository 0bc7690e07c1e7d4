"""Screen (2026-12-01): can a gate from 11 simple body features (size, box, materials, height, footprint) pick, per body, which of the 17 committed students
to use? A k-NN over the other bodies, leave-one-set-out and leave-one-body-out, on the selection's bodies.csv. Run from
the repository root: python lab/results/control_student/selection/gate_cv.py"""
import csv, numpy as np
sets=['design_unseen','grown','hand_built']
G=np.concatenate([np.load('lab/results/heldout_bodies/%s.npy'%s) for s in sets])
S=np.concatenate([[i]*len(np.load('lab/results/heldout_bodies/%s.npy'%s)) for i,s in enumerate(sets)])
rows=list(csv.DictReader(open('lab/results/control_student/selection/bodies.csv')))
names=[k[len('mean_command_'):] for k in rows[0] if k.startswith('mean_command_')]
V=np.array([[float(r['mean_command_'+n]) for r in rows] for n in names])  # [C, M]
P=np.array([float(r['per_body_mean_command']) for r in rows])
def feats(g):
    f=[]
    filled=g>0; idx=np.argwhere(filled); lo,hi=idx.min(0),idx.max(0)+1; dims=hi-lo
    n=filled.sum()
    f += [n, *dims, *(np.bincount(g[filled],minlength=4)[1:]/n), idx[:,2].mean()-lo[2], (idx[:,2]==lo[2]).sum()/n,
          dims[0]/max(dims[1],1), n/np.prod(dims)]
    return f
X=np.array([feats(g) for g in G],float); X=(X-X.mean(0))/(X.std(0)+1e-9)
def gate_pick(train, test, kind):
    picks=[]
    for j in test:
        if kind=='knn':
            d=((X[train]-X[j])**2).sum(1); nn=train[np.argsort(d)[:7]]
            score=V[:,nn].mean(1)  # students' mean move on the nearest training bodies
        picks.append(np.argmax(score))
    return np.array(picks)
for kind in ['knn']:
    chosen=np.zeros(len(rows))
    for s in range(3):
        test=np.where(S==s)[0]; train=np.where(S!=s)[0]
        pk=gate_pick(train,test,kind); chosen[test]=V[pk,test]
    print(kind, 'leave-one-set-out gate: frac %.3f'%(chosen.sum()/P.sum()))
    chosen=np.zeros(len(rows))
    for j in range(len(rows)):
        train=np.array([i for i in range(len(rows)) if i!=j]); chosen[j]=V[gate_pick(train,[j],kind)[0],j]
    print(kind, 'leave-one-body-out gate: frac %.3f'%(chosen.sum()/P.sum()))
print('best single student (hindsight): %.3f'%(V.sum(1).max()/P.sum()), 'mean student %.3f'%(V.sum(1).mean()/P.sum()), 'oracle %.3f'%(V.max(0).sum()/P.sum()))
