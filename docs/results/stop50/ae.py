import json,sys,statistics as st,random
from collections import defaultdict
d=defaultdict(lambda: defaultdict(dict))
for line in open(sys.argv[1]):
    v,rep,js=line.split(' ',2); j=json.loads(js)
    d[(j['replicas'],j['size'])][v][int(rep)]=j['median_us']
a,b=sys.argv[2:4]
for k in sorted(d):
    reps=sorted(set(d[k][a])&set(d[k][b]))
    r=[d[k][b][x]/d[k][a][x] for x in reps]
    random.seed(1)
    bs=sorted(st.median(random.choices(r,k=len(r))) for _ in range(2000))
    print(f"{k[0]} replicas {k[1]} B, {len(reps)} pairs: {a} {st.median(d[k][a][x] for x in reps):.1f} -> {b} {st.median(d[k][b][x] for x in reps):.1f}; ratio {st.median(r):.3f} ({bs[50]:.3f}-{bs[1949]:.3f})")
